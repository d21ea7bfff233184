#!/usr/bin/env python3
"""PyElastica's published plectoneme example (PyElastica 1.0, 150 elements, k = 1e4 self-contact,
10 turns over t in [0, 50], then 50 time units of relaxation), run to its end with snapshots of
the centreline and directors, for the writhe-against-turns curve beside rodsnes's path
(tools/path_plot.py --pyelastica OUT.npz).

Runs in a separate environment that has PyElastica, not rodsnes's:
    python3 -m venv pe-venv && pe-venv/bin/pip install pyelastica==1.0.0
    pe-venv/bin/python tools/pyelastica_path.py OUT.npz [n_elem] [snapshots]

The whole run is 6.0e6 explicit steps (about an hour on a 2-core machine). OUT.npz holds
`time`, `turns` (imposed turns at each snapshot), `wall`, `positions` (k, n+1, 3) and
`directors` (k, 3, 3, n; rows d1, d2, d3 per element). PyElastica's rod lies along +y, d1 = +z.
"""
import sys
import time as _time

import numpy as np
import elastica as ea
from elastica._rotations import _get_rotation_matrix

out = sys.argv[1]
n_elem = int(sys.argv[2]) if len(sys.argv) > 2 else 150
n_snap = int(sys.argv[3]) if len(sys.argv) > 3 else 80
turns = 10
time_twist = 5 * turns
final_time = 50 + time_twist
L, radius = 1.0, 0.025
dt = 0.0025 * L / n_elem
area = np.pi * radius**2
density = 1.0 / (area * L)
nu = 2.0 / density / area
E = 1e6
G = E / 1.5


class Sim(ea.BaseSystemCollection, ea.Constraints, ea.Contact, ea.Forcing, ea.CallBacks, ea.Damping):
    pass


sim = Sim()
rod = ea.CosseratRod.straight_rod(n_elem, np.zeros(3), np.array([0.0, 1.0, 0.0]),
                                  np.array([0.0, 0.0, 1.0]), L, radius, density,
                                  youngs_modulus=E, shear_modulus=G)
rod.velocity_collection[2, n_elem // 2] -= 1e-4
sim.append(rod)
sim.dampen(rod).using(ea.AnalyticalLinearDamper, damping_constant=nu, time_step=dt)


class TwistBC(ea.ConstraintBase):
    """As the example: the end turns about the rod axis in its material frame, slides along the
    axis while twisting, with a small kick at the middle node each twisting step; afterwards
    both ends are held."""
    def __init__(self, p0, p1, d0, d1, **kw):
        super().__init__(**kw)
        theta = 2.0 * turns * np.pi
        axis = d1 @ (-(p1 - p0) / np.linalg.norm(p1 - p0))
        axis /= np.linalg.norm(axis)
        self.final_end = _get_rotation_matrix(-theta, axis.reshape(3, 1)).reshape(3, 3) @ d1
        self.w = theta / time_twist * axis
        self.p0, self.d0 = p0, d0

    def constrain_values(self, system, time):
        if time > time_twist:
            system.position_collection[..., 0] = self.p0
            system.position_collection[0, -1] = 0.0
            system.position_collection[2, -1] = 0.0
            system.director_collection[..., 0] = self.d0
            system.director_collection[..., -1] = self.final_end

    def constrain_rates(self, system, time):
        system.velocity_collection[..., 0] = 0.0
        system.omega_collection[..., 0] = 0.0
        if time > time_twist:
            system.velocity_collection[..., -1] = 0.0
            system.omega_collection[..., -1] = 0.0
        else:
            system.velocity_collection[0, -1] = 0.0
            system.velocity_collection[2, -1] = 0.0
            system.omega_collection[..., -1] = -self.w
            system.velocity_collection[2, system.n_elems // 2] -= 1e-4


sim.constrain(rod).using(TwistBC, constrained_position_idx=(0, -1), constrained_director_idx=(0, -1))
sim.detect_contact_between(rod, rod).using(ea.RodSelfContact, k=1e4, nu=10)
sim.finalize()
stepper = ea.PositionVerlet()
total_steps = int(final_time / dt)
every = max(1, total_steps // n_snap)
t = 0.0
t0 = _time.perf_counter()
snaps = {"time": [], "turns": [], "wall": [], "positions": [], "directors": []}


def snapshot(t):
    snaps["time"].append(t)
    snaps["turns"].append(turns * min(t, time_twist) / time_twist)
    snaps["wall"].append(_time.perf_counter() - t0)
    snaps["positions"].append(rod.position_collection.T.copy())
    snaps["directors"].append(rod.director_collection.copy())


def save():
    np.savez(out, n_elem=n_elem, steps=total_steps, dt=dt,
             **{k: np.array(v) for k, v in snaps.items()})


snapshot(t)
for i in range(1, total_steps + 1):
    t = stepper.step(sim, t, dt)
    if i % every == 0 or i == total_steps:
        snapshot(t)
        save()
        print(f"step {i}/{total_steps} t={t:.2f} wall={snaps['wall'][-1]:.0f}s", flush=True)
print(f"done: {total_steps} steps, wall {snaps['wall'][-1]:.0f} s")
