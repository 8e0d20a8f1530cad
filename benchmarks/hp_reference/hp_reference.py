"""High-precision reference for the 200-link column benchmark (M q'' + K q = 0, v0 = 0) with
ball arithmetic (python-flint / Arb). Two independent methods:

  E: certified eigendecomposition of B = M^-1 K (acb_mat.eig, right vectors, enclosures):
     q(t) = R cos(sqrt(L) t) R^-1 x0,  v(t) = -R sqrt(L) sin(sqrt(L) t) R^-1 x0, at all 641 times.
  C: cosine/sine matrix functions by Taylor series at h = t_end / 2^k with a rigorous tail bound,
     then k doublings C(2h) = 2 C(h)^2 - I, S(2h) = 2 S(h) C(h)  (S(t) = sin(t sqrt B)/sqrt B),
     q = C x0, v = -B S x0; gives t_end, t_end/2, t_end/4, ...

Inputs are the exact float64 M, K, x0 and output times saved by run_femdual.py.
"""
import os
WORK = os.environ.get("HP_WORK", "/tmp/hp_reference")  # scratch directory for the .npz files
os.makedirs(WORK, exist_ok=True)

import sys, time, math
import numpy as np
from flint import arb_mat, acb_mat, arb, acb, ctx

d = np.load(WORK + "/femdual.npz")
M, K, x0, tt = d["M"], d["K"], d["x0"], d["t"]
tt = np.concatenate([tt, float(tt[-1]) / 2.0 ** np.arange(1, 4)])  # + t_end/2, /4, /8 for method C
n = len(x0)
out = {}

def to_np(col_list):
    mids = np.array([[float(c.mid()) for c in row] for row in col_list])
    rads = np.array([[float(c.rad()) for c in row] for row in col_list])
    return mids, rads

# ---- method E ------------------------------------------------------------------------
def method_E(prec):
    ctx.prec = prec
    t0 = time.time()
    B = arb_mat(M.tolist()).solve(arb_mat(K.tolist()))
    E, R = acb_mat(B).eig(right=True)
    print(f"[E prec={prec}] eig {time.time()-t0:.1f}s", flush=True)
    c = R.solve(acb_mat([[float(v)] for v in x0]))
    lam0 = min(E, key=lambda e: abs(e.real.mid()))
    print("  lowest eigenvalue", lam0.real.str(25, radius=True), " max |Im|:",
          max(float(abs(e.imag).upper()) for e in E))
    w = [e.sqrt() for e in E]
    # coefficient of x0 outside the lowest mode
    kk = min(range(n), key=lambda i: abs(E[i].real.mid()))
    others = [(i, c[i, 0]) for i in range(n) if i != kk]
    print("  |c_lowest| =", float(abs(c[kk, 0]).mid()), " max |c_other| =",
          max(float(abs(ci).mid()) for _, ci in others))
    Cx = acb_mat(n, len(tt)); Sv = acb_mat(n, len(tt))
    for j, t in enumerate(tt):
        ta = arb(float(t))
        for i in range(n):
            arg = w[i] * ta
            Cx[i, j] = arg.cos() * c[i, 0]
            Sv[i, j] = -w[i] * arg.sin() * c[i, 0]
    X = R * Cx; V = R * Sv
    xm, xr = to_np([[X[i, j].real for i in range(n)] for j in range(len(tt))])
    vm, vr = to_np([[V[i, j].real for i in range(n)] for j in range(len(tt))])
    xi = max(float(abs(X[i, j].imag).upper()) for i in range(n) for j in range(len(tt)))
    print(f"  max radius x {xr.max():.2e}  v {vr.max():.2e}  max |Im| {xi:.1e}  "
          f"({time.time()-t0:.1f}s)", flush=True)
    return xm, xr, vm, vr

# ---- method C ------------------------------------------------------------------------
def method_C(prec, t_end):
    ctx.prec = prec
    t0 = time.time()
    B = arb_mat(M.tolist()).solve(arb_mat(K.tolist()))
    normB = max(sum(float(abs(B[i, j]).upper()) for j in range(n)) for i in range(n))
    k = 0
    while (t_end / 2**k) ** 2 * normB > 0.25:
        k += 1
    h = arb(t_end) / 2**k  # exact
    Y = B * (h * h)
    y = float((t_end / 2**k) ** 2 * normB) * (1 + 1e-12)
    # J terms: tail sum_{j>J} y^j/(2j)! <= 2 y^(J+1)/(2J+2)!
    J = 1
    while math.log2(2) + (J + 1) * math.log2(y) - math.lgamma(2 * J + 3) / math.log(2) > -prec - 20:
        J += 1
    tail = 2 * y ** (J + 1) / math.factorial(2 * J + 2)  # also bounds the sine series' tail
    I = arb_mat(n, n)
    for i in range(n):
        I[i, i] = 1
    C = I * 1; S = I * 1; P = I * 1
    for j in range(1, J + 1):
        P = P * Y
        C = C + P * (arb((-1) ** j) / arb(math.factorial(2 * j)))
        S = S + P * (arb((-1) ** j) / arb(math.factorial(2 * j + 1)))
    tb = arb(0, tail)
    for i in range(n):
        for j in range(n):
            C[i, j] += tb; S[i, j] += tb
    S = S * h
    for i in range(n):
        for j in range(n):
            S[i, j] += arb(0, 0)  # (h*tail already below 2^-prec)
    print(f"[C prec={prec}] k={k} doublings, ||h^2 B||={y:.3f}, J={J} terms, tail={tail:.1e}, "
          f"{time.time()-t0:.1f}s", flush=True)
    xv = arb_mat([[float(v)] for v in x0])
    res = {}
    for m in range(k):
        C, S = 2 * (C * C) - I, 2 * (S * C)
        level = k - 1 - m  # C = C(t_end / 2^level)
        if level <= 3:
            X = C * xv; V = -(B * (S * xv))
            xm, xr = to_np([[X[i, 0] for i in range(n)]]); vm, vr = to_np([[V[i, 0] for i in range(n)]])
            res[level] = (xm[0], xr[0], vm[0], vr[0])
            print(f"  t_end/2^{level}: max rad x {xr.max():.2e} v {vr.max():.2e}", flush=True)
    print(f"  done {time.time()-t0:.1f}s", flush=True)
    return res

if __name__ == "__main__":
    which = sys.argv[1]
    prec = int(sys.argv[2])
    if which == "E":
        xm, xr, vm, vr = method_E(prec)
        np.savez(f"{WORK}/hpE_{prec}.npz", x=xm, xr=xr, v=vm, vr=vr, t=tt)
    else:
        t_end = float(tt[-1])
        res = method_C(prec, t_end)
        np.savez(f"{WORK}/hpC_{prec}.npz", t_end=t_end,
                 **{f"{q}{l}": res[l][i] for l in res for i, q in enumerate(("x", "xr", "v", "vr"))})
