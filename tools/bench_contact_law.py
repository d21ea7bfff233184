"""Cost of one contact evaluation (energy, residual, tangent) under the two contact laws, on the
plectoneme's strands in line contact at 9.72 turns (tests/data/plectoneme_9.72_line_contact.npy,
60 cubic elements, serial): the closest-point law with contact zones (-contact_model projection)
against the pair potential (-contact_model potential).  Interleaved repeats, medians, one run:

    .venv/bin/python tools/bench_contact_law.py
"""
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "tests"))
from test_contact_math import Rod  # noqa: E402
from rodsnes.contact import ContactKernel  # noqa: E402
from rodsnes.contact_potential import PotentialKernel  # noqa: E402

X = np.load(os.path.join(ROOT, "tests", "data", "plectoneme_9.72_line_contact.npy"))
eps, mu = 0.025, 5.754172062186161e7
rod = Rod(X, 3, False, 1.0, eps=eps, mu=mu, delta=np.pi*eps, nqc=5, reach=0.125)
kp = ContactKernel(3, 5, eps, mu, rod.delta, 1.0, rod.nelem, False, segments=True)
kq = PotentialKernel(3, 5, eps, mu, rod.delta, 1.0, rod.nelem, False)
pairs = rod.pairs(X); xe = X[rod.conn]
T = {"projection": [], "potential": []}
for rep in range(5):
    for name, k in (("projection", kp), ("potential", kq)):
        t = time.perf_counter(); out = k.evaluate(rod.ids, xe, rod.ids, xe, pairs, tangent=True); T[name].append(time.perf_counter() - t)
for n, v in T.items(): print(n, "median s", np.median(v))
print("ratio", np.median(T["projection"]) / np.median(T["potential"]), "nqp", kq.nqp, "pairs", len(pairs))
