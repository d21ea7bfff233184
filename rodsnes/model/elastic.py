"""Cosserat (Simo-Reissner) rod strain energy with quaternion-projection interpolation.

Rotations: per node a unit quaternion q_a; inside an element (signs aligned so that
q_a . q_0 >= 0)  p(s) = sum_a N_a(s) q_a,  R(s) = Rq(p)/|p|^2   (METHOD_NOTES.md,
projection-based FE of Grohs-Hardering-Sander: objective and path-independent).
Strains (slides "Strains measures"), with z = (p, p', r') in R^11:

    v = R^T r'          = Rq(p)^T r' / |p|^2          (shear v1, v2; extension v3)
    u = vee(R^T R')     = 2 vec(conj(p) * p') / |p|^2  (flexures u1, u2; twist u3)

Both numerators are polynomials with constant coefficient tensors:
    [Rq(p)^T r']_k = T_kijl p_i p_j r'_l,      vec(conj(p) * p')_k = A_kij p_i p'_j,
so e(z) = (v, u) = Nz(z) / |p|^2 has closed-form first and second derivatives.

Energy density (quadratic hyperelastic law, diagonal stiffness C = diag(EA.. see below)):
    W = 1/2 (e - e0)^T C (e - e0),  C = diag(GA1, GA2, EA, EI1, EI2, GJ),
    material stress resultants S = C (e - e0) = (R^T n, R^T m)  (slides "Constitutive relations").
    W_z = De^T S,     W_zz = De^T C De + sum_k S_k D2e_k.
Newton unknowns per node: (r_a, theta_a), q_a(theta) = qexp(theta_a) * q_a
(R_a <- exp(theta_a^x) R_a); with B(q) = dq/dtheta at 0 = 1/2 [-qv^T; q0 I - qv^x]:
    g_a  = (dE/dr_a, B(q_a)^T dE/dq_a)           (force balance, spatial moment balance)
    H_ab = T_a^T (d2E/dy_a dy_b) T_b - delta_ab 1/4 (q_a . dE/dq_a) I_3 on the theta block,
and the consistent derivative of the spatial residual adds -1/2 (g_a)_theta^x on that block.

Thickness bound on bending (with self-contact, ``set_curvature_limit``).  A rod of radius eps
cannot bend its centreline to a radius below eps; the penalty

    W_kappa = mu_kappa/2 <kappa - kappa_max>^2,   kappa = |(u1, u2)|,   kappa_max = 1 / eps,
    S_u12  += mu_kappa <kappa - kappa_max> n,     n = (u1, u2) / kappa,
    C_u12  += mu_kappa [ (1 - kappa_max/kappa) I + (kappa_max/kappa) n n^T ]     (kappa > kappa_max)

completes the contact model: with curvature <= 1/eps, two points at arclength distance t <= pi eps
are at least 2 eps sin(t / 2 eps) apart and no pair closer than pi eps can be double-critical
(the curve must turn by pi between them, Schur's comparison theorem), so the exclusion
delta = pi eps of the contact term hides no penetration (thickness >= eps in the sense of
Gonzalez & Maddocks).  kappa is the flexure of the director frame: the centreline curvature in
the unshearable (Kirchhoff) limit, up to O(shear strain) otherwise.
"""
import numpy as np

from rodsnes.profiling import logged
from rodsnes.model import fe, so3
from rodsnes.model import elastic_compiled


def _coefficient_tensors():
    eps = np.zeros((3, 3, 3))
    eps[0, 1, 2] = eps[1, 2, 0] = eps[2, 0, 1] = 1.0
    eps[0, 2, 1] = eps[2, 1, 0] = eps[1, 0, 2] = -1.0
    A = np.zeros((3, 4, 4))           # w_k = A_kij p_i p'_j = [p0 pv' - p0' pv - pv x pv']_k
    T = np.zeros((3, 4, 4, 3))        # g_k = T_kijl p_i p_j r'_l = [Rq(p)^T r']_k
    for k in range(3):
        A[k, 0, 1 + k] += 1.0
        A[k, 1 + k, 0] -= 1.0
        A[k, 1:, 1:] -= eps[k]
        T[k, 0, 0, k] += 1.0
        for m in range(3):
            T[k, 1 + m, 1 + m, k] -= 1.0
            T[k, 1 + k, 1 + m, m] += 2.0
            T[k, 0, 1 + m, :] -= 2.0 * eps[k, m, :]
    T = 0.5 * (T + T.transpose(0, 2, 1, 3))
    return A, T


_A, _T = _coefficient_tensors()
# the same tensors as matrices over outer products, so that the numerators are matrix products
# (a 4-operand einsum has no cheaper contraction path: numpy runs it as one nested loop)
_T_PP = _T.transpose(1, 2, 0, 3).reshape(16, 9)     # (p p^T) -> d g_k / d r'_l   (k, l)
_T_PR = _T.transpose(2, 3, 0, 1).reshape(12, 12)    # (p r'^T) -> 1/2 d g_k / d p_i  (k, i)
_A_PD = _A.transpose(1, 2, 0).reshape(16, 3)        # (p p'^T) -> w_k


def _outer(a, b):
    """a_i b_j flattened over (i, j): (..., len(a) len(b))."""
    return (a[..., :, None] * b[..., None, :]).reshape(a.shape[:-1] + (a.shape[-1] * b.shape[-1],))


def strain_measures(p, dp, dr, derivatives=0):
    """Reference (numpy) form: e = (v, u) at points with interpolated p (...,4), p' (...,4), r' (...,3).

    derivatives=0: e (...,6); 1: (e, De (...,6,11)); 2: (e, De, D2e (...,6,11,11)).
    """
    n2 = np.einsum("...i,...i->...", p, p)
    shp = p.shape[:-1]
    Rt = (_outer(p, p) @ _T_PP).reshape(shp + (3, 3))            # dg/dr' = Rq(p)^T
    g = (Rt @ dr[..., :, None])[..., 0]
    w = _outer(p, dp) @ _A_PD
    Nz = np.concatenate([g, 2.0 * w], axis=-1)
    e = Nz / n2[..., None]
    if derivatives == 0:
        return e
    DN = np.zeros(shp + (6, 11))
    DN[..., :3, 0:4] = 2.0 * (_outer(p, dr) @ _T_PR).reshape(shp + (3, 4))
    DN[..., :3, 8:11] = Rt
    DN[..., 3:, 0:4] = 2.0 * np.einsum("kij,...j->...ki", _A, dp)
    DN[..., 3:, 4:8] = 2.0 * np.einsum("kij,...i->...kj", _A, p)
    Dn2 = np.zeros(shp + (11,))
    Dn2[..., 0:4] = 2.0 * p
    inv = 1.0 / n2
    De = DN * inv[..., None, None] - Nz[..., :, None] * Dn2[..., None, :] * (inv**2)[..., None, None]
    if derivatives == 1:
        return e, De
    D2N = np.zeros(shp + (6, 11, 11))
    D2N[..., :3, 0:4, 0:4] = 2.0 * np.einsum("kijl,...l->...kij", _T, dr)
    cross = 2.0 * np.einsum("kijl,...j->...kil", _T, p)
    D2N[..., :3, 0:4, 8:11] = cross
    D2N[..., :3, 8:11, 0:4] = np.swapaxes(cross, -1, -2)
    D2N[..., 3:, 0:4, 4:8] = 2.0 * _A
    D2N[..., 3:, 4:8, 0:4] = 2.0 * np.swapaxes(_A, -1, -2)
    D2n2 = np.zeros((11, 11))
    D2n2[0:4, 0:4] = 2.0 * np.eye(4)
    outer = DN[..., :, :, None] * Dn2[..., None, None, :]
    D2e = (D2N * inv[..., None, None, None]
           - (outer + np.swapaxes(outer, -1, -2)) * (inv**2)[..., None, None, None]
           - Nz[..., :, None, None] * D2n2 * (inv**2)[..., None, None, None]
           + 2.0 * Nz[..., :, None, None] * (Dn2[..., None, :, None] * Dn2[..., None, None, :])
           * (inv**3)[..., None, None, None])
    return e, De, D2e


def compiled_available():
    """The fused C kernel (rodsnes/model/_elastic_kernel.c) is built and loads."""
    return elastic_compiled.available()


def align_signs(qe):
    """Flip element quaternions so that q_a . q_0 >= 0 (q and -q are the same rotation)."""
    sgn = np.where(np.einsum("eai,ei->ea", qe, qe[:, 0, :]) < 0.0, -1.0, 1.0)
    return qe * sgn[..., None]


def B_matrix(q):
    """dq/dtheta at theta = 0 for q(theta) = qexp(theta) * q:  1/2 [-qv^T; q0 I - qv^x]."""
    B = np.zeros(q.shape[:-1] + (4, 3))
    q0, qv = q[..., 0], q[..., 1:]
    B[..., 0, :] = -0.5 * qv
    B[..., 1:, :] = 0.5 * q0[..., None, None] * np.eye(3)
    B[..., 1, 1] += 0.5 * qv[..., 2]
    B[..., 1, 2] -= 0.5 * qv[..., 1]
    B[..., 2, 0] -= 0.5 * qv[..., 2]
    B[..., 2, 2] += 0.5 * qv[..., 0]
    B[..., 3, 0] += 0.5 * qv[..., 1]
    B[..., 3, 1] -= 0.5 * qv[..., 0]
    return B


class ElasticRod:
    """Elastic energy term over a set of elements (vectorised over element x quad point).

    stiffness: (GA1, GA2, EA, EI1, EI2, GJ); order p; nq Gauss points; element length h.
    e0: (ne, nq, 6) stress-free strains (set with set_reference).

    Three implementations of ``element_terms`` give the same numbers (to 1e-12, tests/
    test_elastic.py and tests/test_elastic_compiled.py):
      compiled   a fused C kernel (rodsnes/model/_elastic_kernel.c, built by ``pip install -e .``),
                 one pass per element; the default when it is built;
      numpy      batched matrix products over (element x point) (``element_terms_numpy``);
      reference  the einsum transcription of the formulas (``element_terms_reference``).
    ``kernel`` chooses: "auto" (compiled if built, else numpy), "compiled", "numpy" or
    "reference" (-rod_kernel).
    """

    def __init__(self, order, nq, h, stiffness, kernel="auto"):
        self.p = order
        self.h = h
        self.nq = nq
        xi, w = fe.gauss_legendre(nq)
        N, dN, _ = fe.lagrange(order, xi)
        self.N = N
        self.dN = dN * (2.0 / h)            # d/ds
        self.wJ = w * (h / 2.0)
        self.C = np.asarray(stiffness, dtype=float)
        self.e0 = None
        self.kappa_max = None           # thickness bound on bending (set_curvature_limit)
        self.mu_kappa = 0.0
        # G maps raw nodal dofs y_a = (q_a (4), x_a (3)) to z = (p, p', r') at each point
        nn = order + 1
        G = np.zeros((nq, 11, nn, 7))
        for a in range(nn):
            G[:, 0:4, a, 0:4] = N[:, a, None, None] * np.eye(4)
            G[:, 4:8, a, 0:4] = self.dN[:, a, None, None] * np.eye(4)
            G[:, 8:11, a, 4:7] = self.dN[:, a, None, None] * np.eye(3)
        self.G = G.reshape(nq, 11, nn * 7)
        self._batched_constants()
        self.kernel = self._choose_kernel(kernel)
        self._ws = None             # the compiled kernel's output arrays for ``reuse``

    # -- set-up ---------------------------------------------------------------------
    def _batched_constants(self):
        """Constant matrices of the batched kernel.  The raw gradient is
        graw = sum_q wJ_q G_q^T W_z (Gw); the raw Hessian  sum_q wJ_q G_q^T W_zz G_q  splits by
        the Kronecker structure of G into shape-function products: (p, p') x (p, p') blocks with
        M[(q, s, t), (a, b)] = wJ_q Phi_s,a Phi_t,b (Phi = (N, N')), (p, p') x r' with Mqx, and
        r' x r' with Mxx."""
        nq, nn = self.N.shape
        Phi = np.stack([self.N, self.dN], axis=1)                        # (q, s, a)
        wJ = self.wJ
        self._Gw = np.ascontiguousarray((wJ[:, None, None] * self.G).reshape(nq * 11, nn * 7))
        self._Mqq = (wJ[:, None, None, None, None] * Phi[:, :, None, :, None]
                     * Phi[:, None, :, None, :]).reshape(nq * 4, nn * nn)
        self._Mqx = (wJ[:, None, None, None] * Phi[:, :, :, None]
                     * self.dN[:, None, None, :]).reshape(nq * 2, nn * nn)
        self._Mxx = (wJ[:, None, None] * self.dN[:, :, None] * self.dN[:, None, :]).reshape(nq, nn * nn)
        # coefficient tensors of the strain numerators, reshaped for matrix products
        self._Tj = np.ascontiguousarray(_T.transpose(2, 0, 1, 3).reshape(4, 36))   # p_j -> (k,i,l)
        self._Tl = np.ascontiguousarray(_T.transpose(0, 3, 1, 2).reshape(9, 16))   # (k,l) -> (i,j)
        self._Aj = np.ascontiguousarray(_A.transpose(2, 0, 1).reshape(4, 12))      # p'_j -> (k,i)
        self._Ai = np.ascontiguousarray(_A.transpose(1, 0, 2).reshape(4, 12))      # p_i -> (k,j)
        self._A2 = np.ascontiguousarray(2.0 * _A.reshape(3, 16))                   # m_k -> (i,j)

    def _choose_kernel(self, kernel):
        if kernel not in ("auto", "compiled", "numpy", "reference"):
            raise ValueError(f"unknown elastic kernel {kernel!r}: use auto, compiled, numpy or reference")
        if kernel in ("auto", "compiled"):
            if compiled_available():
                return "compiled"
            if kernel == "compiled":
                raise RuntimeError("the compiled elastic kernel is not built: run `make install` "
                                   "(pip install -e .) or use -rod_kernel numpy")
            return "numpy"
        return kernel

    def interpolate(self, qe, xe):
        """(p, p', r') at the quadrature points of elements with nodal qe (ne,p+1,4), xe."""
        qe = align_signs(qe)
        return qe, self.N @ qe, self.dN @ qe, self.dN @ xe

    def _strain_parts(self, p, dp, dr):
        """At n points (flattened): |p|^2, the strain numerators Nz (n,6) and their derivative
        DN = dNz/dz (n,6,11), and Tp = T_kijl p_j (n,3,4,3) (module docstring: e = Nz / |p|^2)."""
        n = p.shape[0]
        n2 = np.einsum("ni,ni->n", p, p)
        Tp = (p @ self._Tj).reshape(n, 3, 4, 3)                         # (k, i, l)
        DN = np.zeros((n, 6, 11))
        DN[:, :3, 0:4] = 2.0 * (Tp @ dr[:, None, :, None])[..., 0]       # 2 T_kijl p_j r'_l
        DN[:, :3, 8:11] = (p[:, None, None, :] @ Tp)[:, :, 0, :]         # T_kijl p_i p_j
        DN[:, 3:, 0:4] = 2.0 * (dp @ self._Aj).reshape(n, 3, 4)
        DN[:, 3:, 4:8] = 2.0 * (p @ self._Ai).reshape(n, 3, 4)
        Nz = np.empty((n, 6))
        Nz[:, :3] = (DN[:, :3, 8:11] @ dr[:, :, None])[..., 0]
        Nz[:, 3:] = (DN[:, 3:, 4:8] @ dp[:, :, None])[..., 0]             # 2 w
        return n2, Nz, DN, Tp

    def strains(self, qe, xe):
        """Material strains e = (v, u) (ne, nq, 6) at the quadrature points (in C with the
        compiled kernel: 66 ms in numpy for 10^4 cubic elements, the reference strains of every
        problem made)."""
        if self.kernel == "compiled":
            return elastic_compiled.strains(self.N, self.dN, qe, xe)
        return self.strains_numpy(qe, xe)

    def strains_numpy(self, qe, xe):
        """strains in numpy (the compiled kernel's reference)."""
        _, p, dp, dr = self.interpolate(qe, xe)
        shp = p.shape[:-1]
        p, dp, dr = p.reshape(-1, 4), dp.reshape(-1, 4), dr.reshape(-1, 3)
        n2 = np.einsum("ni,ni->n", p, p)
        Tpp = ((p @ self._Tj).reshape(-1, 3, 4, 3) * p[:, None, :, None]).sum(axis=2)   # (k, l)
        e = np.empty((len(p), 6))
        e[:, :3] = (Tpp @ dr[:, :, None])[..., 0]
        e[:, 3:] = 2.0 * ((p @ self._Ai).reshape(-1, 3, 4) @ dp[:, :, None])[..., 0]
        return (e / n2[:, None]).reshape(shp + (6,))

    def set_reference(self, e0):
        self.e0 = np.asarray(e0, dtype=float)

    def set_curvature_limit(self, kappa_max, mu):
        """Penalise flexure above kappa_max with stiffness mu (W_kappa in the module docstring)."""
        self.kappa_max, self.mu_kappa = float(kappa_max), float(mu)

    def law(self, e, e0, tangent=False):
        """Energy density W, stress S = dW/de and (tangent=True) the curvature bound's part of
        the material tangent, on the (u1, u2) block (None when no point exceeds the bound):

            W = 1/2 (e - e0)^T C (e - e0) + mu_kappa/2 <kappa - kappa_max>^2."""
        de = e - e0
        S = de * self.C
        W = 0.5 * np.einsum("...k,...k->...", de, S)
        if self.kappa_max is None:
            return W, S, None
        ub = e[..., 3:5]
        kappa = np.sqrt(np.einsum("...i,...i->...", ub, ub))
        over = np.maximum(kappa - self.kappa_max, 0.0)
        if not np.any(over > 0.0):
            return W, S, None
        W = W + 0.5 * self.mu_kappa * over**2
        safe = np.where(over > 0.0, kappa, 1.0)
        n = ub / safe[..., None]
        S[..., 3:5] += (self.mu_kappa * over)[..., None] * n
        if not tangent:
            return W, S, None
        ratio = np.where(over > 0.0, self.kappa_max / safe, 0.0)
        active = (over > 0.0).astype(float)
        Cb = self.mu_kappa * ((active - ratio)[..., None, None] * np.eye(2)
                              + ratio[..., None, None] * n[..., :, None] * n[..., None, :])
        return W, S, Cb

    def max_flexure(self, qe, xe):
        """Largest flexure |(u1, u2)| at the quadrature points of the elements (0 for none)."""
        u = self.strains(qe, xe)[..., 3:5]
        return float(np.sqrt(np.einsum("...i,...i->...", u, u)).max()) if u.size else 0.0

    def energy(self, qe, xe, e0=None):
        """E = sum_e sum_q wJ W(e, e0): in C where the compiled kernel is the rod's
        kernel (the line searches' energy), else in numpy."""
        e0 = self.e0 if e0 is None else e0
        if self.kernel == "compiled" and len(qe):
            return float(np.sum(elastic_compiled.element_energy(self, qe, xe, e0)))
        W, _, _ = self.law(self.strains(qe, xe), e0)
        return float(np.sum(W @ self.wJ))

    def node_energy(self, q, r, conn, e0=None):
        """energy(q[conn], r[conn], e0) with the elements' nodes gathered in the compiled
        kernel's pass (elastic_compiled.node_energy: no gathered arrays), else in numpy."""
        if self.kernel == "compiled" and len(conn):
            return float(np.sum(elastic_compiled.node_energy(self, q, r, conn, e0)))
        return self.energy(np.take(q, conn, axis=0), np.take(r, conn, axis=0), e0)

    def stress(self, qe, xe, e0=None):
        """Material stress resultants S = dW/de = (R^T n, R^T m) at quadrature points."""
        e0 = self.e0 if e0 is None else e0
        return self.law(self.strains(qe, xe), e0)[1]

    @logged("ElasticKernel")
    def element_terms(self, qe, xe, e0=None, tangent=True, symmetric=False, reuse=False,
                      comps=None):
        """Element residuals (ne, p+1, 6) and tangents (ne, 6(p+1), 6(p+1)) in the
        Newton unknowns (r, theta) per node, plus the energy of each element.
        ``reuse``: the compiled kernel writes into arrays kept on the rod (_workspace: no fresh
        arrays each call; the caller consumes them before the next call: RodProblem's residual
        and Jacobian).

        The residual seen by SNES at a trial increment theta is the spatial moment
        F(theta) = J_l(theta)^{-T} grad f(theta) (f = E o exp chart), so its exact derivative
        at theta = 0 is  H - 1/2 g_theta^x  on each node's theta-theta block (symmetric=False,
        the default: the consistent Newton tangent).  symmetric=True returns the Hessian H of
        the energy in the exponential chart (for inertia / stability: equal at equilibrium).
        Computed by the kernel chosen at construction (class docstring).  ``comps``: the
        tangents cut to these components of every node, (ne, c(p+1), c(p+1)) with rows and
        columns (node, component) (the planar step's in-plane block: planar.ComponentView);
        the compiled kernel cuts each element's tangent as it is made."""
        if self.kernel == "compiled":
            nc = 6 if comps is None else len(comps)
            out = self._workspace(len(qe), tangent, nc) if reuse else None
            return elastic_compiled.element_terms(self, qe, xe, e0, tangent, symmetric, out=out,
                                                  comps=comps)
        if self.kernel == "reference":
            out = self.element_terms_reference(qe, xe, e0, tangent, symmetric)
        else:
            out = self.element_terms_numpy(qe, xe, e0, tangent, symmetric)
        if comps is None or out[2] is None:
            return out
        idx = (6 * np.arange(self.p + 1)[:, None] + np.asarray(comps)[None, :]).ravel()
        return out[0], out[1], out[2][:, idx[:, None], idx[None, :]]

    @logged("ElasticKernel")
    def node_residual(self, q, r, conn, e0=None):
        """(energy (ne,), residual summed per node (len(q), 6)) at the nodes' quaternions q and
        positions r, the elements' nodes conn (rows of q and r): element_terms of the gathered
        elements without tangent, its rows summed per node in the elements' order; the compiled
        kernel gathers and sums in its pass (elastic_compiled.node_residual)."""
        if self.kernel == "compiled":
            return elastic_compiled.node_residual(self, q, r, conn, e0)
        energy, vec, _ = self.element_terms(np.take(q, conn, axis=0), np.take(r, conn, axis=0),
                                            e0, tangent=False)
        out = np.zeros((len(q), 6))
        np.add.at(out, np.asarray(conn).ravel(), vec.reshape(-1, 6))
        return energy, out

    @logged("ElasticKernel")
    def plane_tangents(self, qe, xe, plane, e0=None, reuse=False):
        """The in-plane tangents (ne, 3(p+1), 3(p+1)) at a state in ``plane`` (model.plane.Plane:
        normal e_axis), rows and columns (node, plane.inplane = (r_P, r_Q, theta_axis), P < Q):
        the tangents of element_terms cut to those components (at a planar state the
        consistent tangent and the Hessian are equal there), which the compiled kernel makes
        from the in-plane strain variables alone, a third of the time of the 3-D tangent
        (elastic_compiled.plane_tangents); the other kernels cut their 3-D tangents.  For
        planar states only: the out-of-plane parts of the state are not seen (the planar
        step's guard watches them, planar.PlanarSystem)."""
        if self.kernel != "compiled":
            return self.element_terms(qe, xe, e0, tangent=True, comps=plane.inplane)[2]
        out = self._workspace(len(qe), True, 3)[2] if reuse else None
        return elastic_compiled.plane_tangents(self, qe, xe, plane.axis, e0, out=out)

    @logged("ElasticKernel")
    def tangents_into(self, q, r, conn, blocks, e0=None, plane=None, comps=None,
                      symmetric=False, store_first=False):
        """The tangents of the elements ``conn`` (rows of the node arrays q, r) added into the
        matrix of ``blocks`` (assembly.ElementBlocks: at its places, the elements it adds
        directly) as the compiled kernel makes them: plane_tangents(..., plane) or
        element_terms(..., tangent=True, symmetric, comps)'s tangents, the same numbers;
        ``store_first``: stored at each block's first addition (ElementBlocks.first, after
        its zero_rest), not added.  Returns False (nothing added) where the kernel is not the
        compiled one."""
        if self.kernel != "compiled":
            return False
        with blocks.values() as ptr:
            elastic_compiled.tangents_into(
                self, q, r, conn, e0, blocks.pos, ptr, blocks.k, blocks.bs,
                axis=-1 if plane is None else plane.axis, comps=comps, symmetric=symmetric,
                first=blocks.first if store_first else None)
        return True

    def _workspace(self, ne, tangent, nc=6):
        """(energy, vec, H or None) arrays kept for ``reuse``: the leading ne elements of arrays
        that only grow (the residual takes all the elements at once, the Jacobian a chunk at a
        time: RodProblem.jacobian; a leading slice of a C-contiguous array is C-contiguous); H
        of nc components a node (``comps``)."""
        nn = self.p + 1
        ws = self._ws
        if ws is None or len(ws[0]) < ne:
            ws = self._ws = [np.empty(ne), np.empty((ne, nn, 6)), None]
        if tangent and (ws[2] is None or len(ws[2]) < ne or ws[2].shape[1] != nc * nn):
            ws[2] = np.empty((ne, nc * nn, nc * nn))
        out = [a if len(a) == ne else a[:ne] for a in ws[:2 + bool(tangent)]]
        return out[0], out[1], out[2] if tangent else None

    def element_terms_numpy(self, qe, xe, e0=None, tangent=True, symmetric=False):
        """element_terms as batched matrix products over (element x point): the first and
        second derivatives of e = Nz(z) / |p|^2 in closed form (no (6, 11, 11) array),

            W_z  = De^T S,
            W_zz = De^T C De + [S.D2N] / |p|^2 - (v Dn2^T + Dn2 v^T) / |p|^4
                   - (S.Nz) D2n2 / |p|^4 + 2 (S.Nz) Dn2 Dn2^T / |p|^6,

        v = DN^T S, Dn2 = (2p, 0, 0), D2n2 = 2 I on the p block; then the shape-function
        contractions with the constant matrices of _batched_constants."""
        e0 = self.e0 if e0 is None else e0
        ne, nn, nq = qe.shape[0], self.p + 1, self.nq
        n = ne * nq
        qa, p, dp, dr = self.interpolate(qe, xe)
        p, dp, dr = p.reshape(n, 4), dp.reshape(n, 4), dr.reshape(n, 3)
        n2, Nz, DN, Tp = self._strain_parts(p, dp, dr)
        inv = 1.0 / n2
        inv2 = inv * inv
        e = Nz * inv[:, None]
        De = DN * inv[:, None, None]
        De[:, :, 0:4] -= (2.0 * inv2)[:, None, None] * (Nz[:, :, None] * p[:, None, :])
        W, S, Cb = self.law(e.reshape(ne, nq, 6), e0, tangent=tangent)
        energy = W @ self.wJ
        S = S.reshape(n, 6)
        Wz = (S[:, None, :] @ De)[:, 0, :]                                # (n, 11)
        graw = (Wz.reshape(ne, nq * 11) @ self._Gw).reshape(ne, nn, 7)
        B = B_matrix(qa)                                                  # (ne, nn, 4, 3)
        vec = np.empty((ne, nn, 6))
        vec[:, :, 0:3] = graw[:, :, 4:7]
        vec[:, :, 3:6] = (graw[:, :, None, 0:4] @ B)[:, :, 0, :]
        if not tangent:
            return energy, vec, None
        Wzz = np.swapaxes(De * self.C[:, None], -1, -2) @ De              # (n, 11, 11)
        if Cb is not None:
            D = De.reshape(ne, nq, 6, 11)[..., 3:5, :]
            Wzz += (np.swapaxes(D, -1, -2) @ (Cb @ D)).reshape(n, 11, 11)
        v = (S[:, None, :] @ DN)[:, 0, :]
        sN = np.einsum("nk,nk->n", S, Nz)
        Sd = S[:, :3]
        Wzz[:, 0:4, 0:4] += (2.0 * inv)[:, None, None] * (
            (Sd[:, :, None] * dr[:, None, :]).reshape(n, 9) @ self._Tl).reshape(n, 4, 4)
        X = (2.0 * inv)[:, None, None] * (Sd[:, None, :] @ Tp.reshape(n, 3, 12))[:, 0, :].reshape(n, 4, 3)
        Wzz[:, 0:4, 8:11] += X
        Wzz[:, 8:11, 0:4] += np.swapaxes(X, -1, -2)
        Y = inv[:, None, None] * (S[:, 3:] @ self._A2).reshape(n, 4, 4)
        Wzz[:, 0:4, 4:8] += Y
        Wzz[:, 4:8, 0:4] += np.swapaxes(Y, -1, -2)
        twop = 2.0 * p
        a = inv2[:, None, None]
        Wzz[:, :, 0:4] -= a * (v[:, :, None] * twop[:, None, :])
        Wzz[:, 0:4, :] -= a * (twop[:, :, None] * v[:, None, :])
        Wzz[:, 0:4, 0:4] += ((8.0 * sN * inv2 * inv)[:, None, None] * (p[:, :, None] * p[:, None, :])
                             - (2.0 * sN * inv2)[:, None, None] * np.eye(4))
        Wzz = Wzz.reshape(ne, nq, 11, 11)
        Wqq = Wzz[:, :, 0:8, 0:8].reshape(ne, nq, 2, 4, 2, 4).transpose(0, 3, 5, 1, 2, 4).reshape(ne * 16, nq * 4)
        Wqx = Wzz[:, :, 0:8, 8:11].reshape(ne, nq, 2, 4, 3).transpose(0, 3, 4, 1, 2).reshape(ne * 12, nq * 2)
        Wxx = Wzz[:, :, 8:11, 8:11].transpose(0, 2, 3, 1).reshape(ne * 9, nq)
        Hqq = (Wqq @ self._Mqq).reshape(ne, 4, 4, nn, nn).transpose(0, 3, 4, 1, 2)    # (e,a,b,i,j)
        Hqx = (Wqx @ self._Mqx).reshape(ne, 4, 3, nn, nn).transpose(0, 3, 4, 1, 2)
        Hxx = (Wxx @ self._Mxx).reshape(ne, 3, 3, nn, nn).transpose(0, 3, 4, 1, 2)
        # T_a: (r, theta) -> (q, x):  q block = B theta, x block = r
        H = np.empty((ne, nn, 6, nn, 6))
        Ht = H.transpose(0, 1, 3, 2, 4)                                    # view (e, a, b, 6, 6)
        BaT = np.swapaxes(B, -1, -2)[:, :, None]
        Ht[..., 0:3, 0:3] = Hxx
        Ht[..., 3:6, 0:3] = BaT @ Hqx
        Ht[..., 0:3, 3:6] = np.swapaxes(Ht[..., 3:6, 0:3], -1, -2).swapaxes(1, 2)
        Ht[..., 3:6, 3:6] = BaT @ (Hqq @ B[:, None, :])
        self._add_chart(Ht, qa, graw, vec, symmetric)
        return energy, vec, H.reshape(ne, nn * 6, nn * 6)

    def _add_chart(self, Ht, qa, graw, vec, symmetric):
        """On each node's theta-theta block (Ht viewed as (e, a, b, 6, 6)): the exponential
        chart's second-order term -1/4 (q_a . dE/dq_a) I, and unless symmetric the spatial
        residual's -1/2 g_theta^x."""
        nn = self.p + 1
        ar = np.arange(nn)
        chart = -0.25 * np.einsum("eai,eai->ea", qa, graw[:, :, 0:4])
        D = Ht[:, ar, ar, 3:6, 3:6] + chart[..., None, None] * np.eye(3)
        if not symmetric:
            D -= 0.5 * so3.hat(vec[:, :, 3:6])
        Ht[:, ar, ar, 3:6, 3:6] = D

    def element_terms_reference(self, qe, xe, e0=None, tangent=True, symmetric=False):
        """element_terms by a direct transcription of the formulas (module docstring; einsums and,
        for the strains, matrix products: strain_measures), with the (6, 11, 11) second
        derivatives of the strains: the reference the fast kernels are tested against."""
        e0 = self.e0 if e0 is None else e0
        qa, p, dp, dr = self.interpolate(qe, xe)
        ne, nn = qe.shape[0], self.p + 1
        if tangent:
            e, De, D2e = strain_measures(p, dp, dr, derivatives=2)
        else:
            e, De = strain_measures(p, dp, dr, derivatives=1)
        W, S, Cb = self.law(e, e0, tangent=tangent)
        energy = np.einsum("q,eq->e", self.wJ, W)
        Wz = np.einsum("eqkz,eqk->eqz", De, S)
        graw = np.einsum("q,qzy,eqz->ey", self.wJ, self.G, Wz, optimize=True).reshape(ne, nn, 7)
        B = B_matrix(qa)
        vec = np.empty((ne, nn, 6))
        vec[:, :, 0:3] = graw[:, :, 4:7]
        vec[:, :, 3:6] = np.einsum("eaij,eai->eaj", B, graw[:, :, 0:4])
        if not tangent:
            return energy, vec, None
        Wzz = (np.einsum("eqkz,k,eqky->eqzy", De, self.C, De, optimize=True)
               + np.einsum("eqk,eqkzy->eqzy", S, D2e))
        if Cb is not None:
            Wzz += np.einsum("eqkz,eqkl,eqly->eqzy", De[..., 3:5, :], Cb, De[..., 3:5, :], optimize=True)
        Hraw = np.einsum("q,qzi,eqzy,qyj->eij", self.wJ, self.G, Wzz, self.G, optimize=True)
        Hraw = Hraw.reshape(ne, nn, 7, nn, 7)
        T = np.zeros((ne, nn, 7, 6))
        T[:, :, 4:7, 0:3] = np.eye(3)
        T[:, :, 0:4, 3:6] = B
        H = np.einsum("eaim,eaibj,ebjn->eambn", T, Hraw, T, optimize=True)
        self._add_chart(H.transpose(0, 1, 3, 2, 4), qa, graw, vec, symmetric)
        return energy, vec, H.reshape(ne, nn * 6, nn * 6)


def strains_at_nodes(order, h, qe, xe, compiled=None):
    """Material strains e = (v, u) (ne, p+1, 6) evaluated at each element's own nodes (the
    output's nodal strains): in C where the compiled kernel is built (``compiled`` None) or
    asked for (True), else in numpy."""
    xi = fe.reference_nodes(order)
    N, dN, _ = fe.lagrange(order, xi)
    if compiled or (compiled is None and elastic_compiled.available()):
        return elastic_compiled.strains(N, dN * (2.0 / h), qe, xe)
    qa = align_signs(qe)
    p = N @ qa
    dp = (dN * (2.0 / h)) @ qa
    dr = (dN * (2.0 / h)) @ xe
    return strain_measures(p, dp, dr)
