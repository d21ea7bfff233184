/* The in-plane tangent of a planar state on LANES elements at once (included by
 * _elastic_kernel.c once for each vector width it builds: LANES 2, SSE2's, and 4, AVX2's, with
 * PLANE(name) its names for that width).  Each quantity of the formulas of _elastic_kernel.c
 * (the in-plane tangent of a planar state) is a vector of the LANES elements' values (GCC's
 * vector extension: the same arithmetic lane by lane, in SIMD registers, bit for bit the
 * scalar formulas'); the element constants come from the scalar helpers lane by lane, the
 * tangents go out transposed in registers, each element's entries a vector at a time. */

/* VD, SPLAT, LANE and the transpose out: _elastic_lanes.h's, included just before for the same
 * width. */

/* The in-plane tangents of the elements at qin[l], xin[l], e0in[l] (l < LANES) into H[l] (those
 * not NULL). */
static ALWAYS_INLINE void PLANE(elements)(const int NN, const Setup *st, const double **qin,
                                         const double **xin, const double **e0in, int axis,
                                         double **H)
{
    const int P = (axis == 0) ? 1 : 0, Q = (axis == 2) ? 1 : 2, ld = 3 * NN;
    /* the element constants, lane by lane: z_a, R_0^T of the unit q_0 / |q_0|, a3 = R_0^T n,
     * R_0 Cv R_0^T, a3^T Cu a3 */
    VD z[MAXNN][2], R0t[3][3], a3[3], CvG[3][3], Cu0, xP[MAXNN], xQ[MAXNN];
    for (int l = 0; l < LANES; l++) {
        double q[MAXNN][4], zl[MAXNN][2], R[3][3];
        align_signs(NN, qin[l], q);
        plane_angles(NN, q, axis, zl);
        const double inv = 1.0 / rotation_numerator(q[0], R);
        for (int i = 0; i < 3; i++)
            for (int j = 0; j < 3; j++) R0t[i][j][l] = R[i][j] * inv;
        for (int a = 0; a < NN; a++) {
            z[a][0][l] = zl[a][0];
            z[a][1][l] = zl[a][1];
            xP[a][l] = xin[l][3 * a + P];
            xQ[a][l] = xin[l][3 * a + Q];
        }
    }
    double nv[3] = {0.0, 0.0, 0.0}, eP[3] = {0.0, 0.0, 0.0}, eQ[3] = {0.0, 0.0, 0.0};
    nv[axis] = 1.0; eP[P] = 1.0; eQ[Q] = 1.0;
    double nxP[3], nxQ[3];
    cross3(nv, eP, nxP);
    cross3(nv, eQ, nxQ);
    for (int k = 0; k < 3; k++) a3[k] = R0t[k][axis];
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            CvG[i][j] = st->C[0] * R0t[0][i] * R0t[0][j] + st->C[1] * R0t[1][i] * R0t[1][j]
                      + st->C[2] * R0t[2][i] * R0t[2][j];
    Cu0 = st->C[3] * a3[0] * a3[0] + st->C[4] * a3[1] * a3[1] + st->C[5] * a3[2] * a3[2];
    VD Hv[(3 * MAXNN) * (3 * MAXNN)];
    for (int i = 0; i < ld * ld; i++) Hv[i] = SPLAT(0.0);

    for (int g = 0; g < st->nq; g++) {
        const double *N = st->N + g * NN, *dN = st->dN + g * NN, w = st->wJ[g];
        VD c = SPLAT(0.0), s = SPLAT(0.0), dc = SPLAT(0.0), ds = SPLAT(0.0);
        VD rP = SPLAT(0.0), rQ = SPLAT(0.0);
        for (int a = 0; a < NN; a++) {
            c += N[a] * z[a][0];   s += N[a] * z[a][1];
            dc += dN[a] * z[a][0]; ds += dN[a] * z[a][1];
            rP += dN[a] * xP[a];
            rQ += dN[a] * xQ[a];
        }
        VD dr[3], m[3], G[3];
        for (int i = 0; i < 3; i++) dr[i] = rP * eP[i] + rQ * eQ[i];
        m[0] = nv[1] * dr[2] - nv[2] * dr[1];
        m[1] = nv[2] * dr[0] - nv[0] * dr[2];
        m[2] = nv[0] * dr[1] - nv[1] * dr[0];
        const VD cs2 = c * c - s * s, tcs = 2.0 * c * s;
        for (int i = 0; i < 3; i++) G[i] = cs2 * dr[i] - tcs * m[i];
        const VD n2 = c * c + s * s, inv = 1.0 / n2, inv2 = inv * inv;
        const VD k = 2.0 * (c * ds - dc * s);
        /* strains, law */
        VD e[6], e0[6], S[6], Cb[4];
        for (int i = 0; i < 3; i++) {
            e[i] = (R0t[i][0] * G[0] + R0t[i][1] * G[1] + R0t[i][2] * G[2]) * inv;
            e[3 + i] = a3[i] * k * inv;
        }
        {
            double lanes[6][LANES];
            for (int i = 0; i < 6; i++)
                for (int l = 0; l < LANES; l++) lanes[i][l] = e0in[l][6 * g + i];
            memcpy(e0, lanes, sizeof(lanes));
        }
        VD W;                           /* (the energy density: not needed here) */
        const VD bound = L(constitutive_law)(st, e, e0, S, &W, Cb);
        VD f[3];
        for (int i = 0; i < 3; i++)
            f[i] = R0t[0][i] * S[0] + R0t[1][i] * S[1] + R0t[2][i] * S[2];
        const VD mk = a3[0] * S[3] + a3[1] * S[4] + a3[2] * S[5];
        const VD Ck = Cu0 + bound * (Cb[0] * a3[0] * a3[0] + (Cb[1] + Cb[2]) * a3[0] * a3[1]
                                     + Cb[3] * a3[1] * a3[1]);
        /* first derivatives in y = (c, s, c', s', r'_P, r'_Q) */
        VD DG[3][6], Dk[6] = {2.0 * ds, -2.0 * dc, -2.0 * s, 2.0 * c, SPLAT(0.0), SPLAT(0.0)};
        for (int i = 0; i < 3; i++) {
            DG[i][0] = 2.0 * c * dr[i] - 2.0 * s * m[i];
            DG[i][1] = -2.0 * s * dr[i] - 2.0 * c * m[i];
            DG[i][2] = DG[i][3] = SPLAT(0.0);
            DG[i][4] = cs2 * eP[i] - tcs * nxP[i];
            DG[i][5] = cs2 * eQ[i] - tcs * nxQ[i];
        }
        const VD Dn2c = 2.0 * c, Dn2s = 2.0 * s;
        const VD Phi = f[0] * G[0] + f[1] * G[1] + f[2] * G[2] + mk * k;
        VD Phy[6], Wy[6], De[4][6];
        for (int j = 0; j < 6; j++) {
            Phy[j] = f[0] * DG[0][j] + f[1] * DG[1][j] + f[2] * DG[2][j] + mk * Dk[j];
            for (int i = 0; i < 3; i++) De[i][j] = DG[i][j] * inv;
            De[3][j] = Dk[j] * inv;
        }
        for (int i = 0; i < 3; i++) {
            De[i][0] -= G[i] * Dn2c * inv2;
            De[i][1] -= G[i] * Dn2s * inv2;
        }
        De[3][0] -= k * Dn2c * inv2;
        De[3][1] -= k * Dn2s * inv2;
        for (int j = 0; j < 6; j++) Wy[j] = Phy[j] * inv;
        Wy[0] -= Phi * Dn2c * inv2;
        Wy[1] -= Phi * Dn2s * inv2;
        /* W_yy: material part D_eps^T W_eps,eps D_eps */
        VD Wyy[6][6], CD[4][6];
        for (int j = 0; j < 6; j++) {
            for (int i = 0; i < 3; i++)
                CD[i][j] = CvG[i][0] * De[0][j] + CvG[i][1] * De[1][j] + CvG[i][2] * De[2][j];
            CD[3][j] = Ck * De[3][j];
        }
        for (int i = 0; i < 6; i++)
            for (int j = i; j < 6; j++)
                Wyy[i][j] = De[0][i] * CD[0][j] + De[1][i] * CD[1][j] + De[2][i] * CD[2][j]
                          + De[3][i] * CD[3][j];
        /* geometric part: Phi_yy / n2 (upper triangle) */
        const VD fr = f[0] * dr[0] + f[1] * dr[1] + f[2] * dr[2];
        const VD fm = f[0] * m[0] + f[1] * m[1] + f[2] * m[2];
        VD fP1 = SPLAT(0.0), fQ1 = SPLAT(0.0), fP2 = SPLAT(0.0), fQ2 = SPLAT(0.0);
        for (int i = 0; i < 3; i++) {
            fP1 += f[i] * (2.0 * c * eP[i] - 2.0 * s * nxP[i]);
            fQ1 += f[i] * (2.0 * c * eQ[i] - 2.0 * s * nxQ[i]);
            fP2 += f[i] * (-2.0 * s * eP[i] - 2.0 * c * nxP[i]);
            fQ2 += f[i] * (-2.0 * s * eQ[i] - 2.0 * c * nxQ[i]);
        }
        Wyy[0][0] += 2.0 * fr * inv;
        Wyy[1][1] -= 2.0 * fr * inv;
        Wyy[0][1] -= 2.0 * fm * inv;
        Wyy[0][4] += fP1 * inv;  Wyy[0][5] += fQ1 * inv;
        Wyy[1][4] += fP2 * inv;  Wyy[1][5] += fQ2 * inv;
        Wyy[0][3] += 2.0 * mk * inv;
        Wyy[1][2] -= 2.0 * mk * inv;
        /* - (Phi_y Dn2^T + Dn2 Phi_y^T) / n2^2 - Phi D2n2 / n2^2 + 2 Phi Dn2 Dn2^T / n2^3 */
        const VD Dn2[2] = {Dn2c, Dn2s};
        for (int i = 0; i < 2; i++)
            for (int j = i; j < 6; j++) {
                VD d = -(Phy[j] * Dn2[i]) * inv2;
                if (j < 2) d += -(Dn2[j] * Phy[i]) * inv2 + 2.0 * Phi * Dn2[i] * Dn2[j] * inv2 * inv;
                if (j == i) d -= 2.0 * Phi * inv2;
                Wyy[i][j] += d;
            }
        for (int i = 0; i < 6; i++)
            for (int j = 0; j < i; j++) Wyy[i][j] = Wyy[j][i];
        /* chain to the nodes, K_ab = w J_a^T W_yy J_b (b >= a): J_a's columns are dN_a e_4,
         * dN_a e_5 (r_P, r_Q) and t_a (theta, in y_0..y_3), so with u4_b = W_4,0:4 t_b,
         * u5_b = W_5,0:4 t_b and v_b = W_0:4,0:4 t_b (per node, not per pair)
         *   K_ab = w [[dN_a dN_b W_44, dN_a dN_b W_45, dN_a u4_b],
         *             [dN_a dN_b W_45, dN_a dN_b W_55, dN_a u5_b],
         *             [dN_b u4_a,      dN_b u5_a,      t_a . v_b]] */
        VD t[MAXNN][4], u4[MAXNN], u5[MAXNN], v[MAXNN][4];
        for (int a = 0; a < NN; a++) {
            t[a][0] = -0.5 * N[a] * z[a][1];  t[a][1] = 0.5 * N[a] * z[a][0];
            t[a][2] = -0.5 * dN[a] * z[a][1]; t[a][3] = 0.5 * dN[a] * z[a][0];
            const VD *ta = t[a];
            u4[a] = Wyy[4][0] * ta[0] + Wyy[4][1] * ta[1] + Wyy[4][2] * ta[2] + Wyy[4][3] * ta[3];
            u5[a] = Wyy[5][0] * ta[0] + Wyy[5][1] * ta[1] + Wyy[5][2] * ta[2] + Wyy[5][3] * ta[3];
            for (int kk = 0; kk < 4; kk++)
                v[a][kk] = Wyy[kk][0] * ta[0] + Wyy[kk][1] * ta[1] + Wyy[kk][2] * ta[2]
                         + Wyy[kk][3] * ta[3];
        }
        const VD W44 = w * Wyy[4][4], W45 = w * Wyy[4][5], W55 = w * Wyy[5][5];
        for (int b = 0; b < NN; b++) {
            const double wdb = w * dN[b];
            for (int a = 0; a <= b; a++) {
                VD *Hab = Hv + (3 * a) * ld + 3 * b;
                const double da = dN[a], dd = da * dN[b], wda = w * da;
                Hab[0] += dd * W44;
                Hab[1] += dd * W45;
                Hab[2] += wda * u4[b];
                Hab[ld] += dd * W45;
                Hab[ld + 1] += dd * W55;
                Hab[ld + 2] += wda * u5[b];
                Hab[2 * ld] += wdb * u4[a];
                Hab[2 * ld + 1] += wdb * u5[a];
                Hab[2 * ld + 2] += w * (t[a][0] * v[b][0] + t[a][1] * v[b][1]
                                        + t[a][2] * v[b][2] + t[a][3] * v[b][3]);
            }
        }
        for (int a = 0; a < NN; a++)
            Hv[(3 * a + 2) * ld + 3 * a + 2] -= 0.25 * w * (
                N[a] * (Wy[0] * z[a][0] + Wy[1] * z[a][1])
                + dN[a] * (Wy[2] * z[a][0] + Wy[3] * z[a][1]));
    }
    /* the lower block triangle */
    for (int a = 0; a < NN; a++)
        for (int b = a + 1; b < NN; b++)
            for (int i = 0; i < 3; i++)
                for (int j = 0; j < 3; j++)
                    Hv[(3 * b + j) * ld + 3 * a + i] = Hv[(3 * a + i) * ld + 3 * b + j];
    L(transpose_out)(Hv, ld * ld, H);
}

/* The in-plane tangents of elements 0..ne-1 (rodsnes_elastic_plane_tangent_lanes' arguments) in
 * groups of LANES; the last group's lanes beyond ne repeat element ne - 1 and write nothing. */
static void PLANE(tangents)(int ne, int nn, const Setup *st, const double *qe, const double *xe,
                            const double *e0, int axis, double *H)
{
    const int nq = st->nq;
#define PLANE_GROUPS(NN)                                                                   \
    for (int e = 0; e < ne; e += LANES) {                                                  \
        const double *qg[LANES], *xg[LANES], *eg[LANES];                                   \
        double *Hg[LANES];                                                                 \
        for (int l = 0; l < LANES; l++) {                                                  \
            const int el = e + l < ne ? e + l : ne - 1;                                    \
            qg[l] = qe + (long)el * 4 * (NN);                                              \
            xg[l] = xe + (long)el * 3 * (NN);                                              \
            eg[l] = e0 + (long)el * 6 * nq;                                                \
            Hg[l] = e + l < ne ? H + (long)el * 9 * (NN) * (NN) : NULL;                    \
        }                                                                                  \
        PLANE(elements)(NN, st, qg, xg, eg, axis, Hg);                                     \
    }
    BY_NODE_COUNT(PLANE_GROUPS)
#undef PLANE_GROUPS
}

/* the end of this width: its macros (the includer's LANES, VD, VI, L, PLANE and
 * _elastic_lanes.h's SPLAT, LANE, PAIR) go */
#undef LANES
#undef VD
#undef VI
#undef L
#undef PLANE
#undef SPLAT
#undef LANE
#undef PAIR
