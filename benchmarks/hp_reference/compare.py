"""Compare fem-dual, its reference (scene.reference) and a direct expm against the
high-precision (Arb) references of hp_reference.py."""
import os
WORK = os.environ.get("HP_WORK", "/tmp/hp_reference")  # scratch directory for the .npz files
os.makedirs(WORK, exist_ok=True)

import numpy as np
d = np.load(WORK + "/femdual.npz")
E = np.load(WORK + "/hpE_512.npz"); E2 = np.load(WORK + "/hpE_256.npz")
C = np.load(WORK + "/hpC_1024.npz")
nt = len(d["t"])
assert np.array_equal(E["t"][:nt], d["t"])
Ex, Ev = E["x"][:nt], E["v"][:nt]
sx, sv = np.abs(Ex).max(), np.abs(Ev).max()
print(f"scales: max|x| = {sx:.6g}, max|v| = {sv:.6g}")
print("\n-- HP self-consistency --")
print(f"E(512 bits) vs E(256 bits): x {np.abs(E['x']-E2['x']).max():.1e}  v {np.abs(E['v']-E2['v']).max():.1e}"
      f"   (ball radii E512: x {E['xr'].max():.1e}, v {E['vr'].max():.1e})")
for l in range(4):
    j = nt + l - 1 if l else nt - 1   # row of t_end/2^l in E
    print(f"E vs C at t_end/2^{l} = {E['t'][j]!r}: x {np.abs(E['x'][j]-C[f'x{l}']).max():.1e}  "
          f"v {np.abs(E['v'][j]-C[f'v{l}']).max():.1e}")

def report(name, x, v, rows=slice(None)):
    ex = np.abs(x - Ex[rows]).max(axis=1); ev = np.abs(v - Ev[rows]).max(axis=1)
    return ex, ev

idx = list(d["idx"]); labels = ["T/4", "T/2", "3T/4", "T"]
print("\n-- errors against the HP reference (max over components) --")
for name, x, v in (("fem-dual", d["x"], d["v"]), ("fem-dual's reference", d["ref_x"], d["ref_v"])):
    ex, ev = report(name, x, v)
    print(f"{name:24s} all {nt} times: x {ex.max():.3e} (rel {ex.max()/sx:.2e}) at t={d['t'][ex.argmax()]:.3f};"
          f"  v {ev.max():.3e} (rel {ev.max()/sv:.2e}) at t={d['t'][ev.argmax()]:.3f}")
    print(" " * 26 + "  ".join(f"{lab}: x {ex[i]:.2e} v {ev[i]:.2e}" for lab, i in zip(labels, idx)))
ex = np.abs(d["direct_x"] - Ex[idx]).max(axis=1); ev = np.abs(d["direct_v"] - Ev[idx]).max(axis=1)
print(f"{'expm (direct expm(tA)z0)':24s}  " + "  ".join(f"{lab}: x {a:.2e} v {b:.2e}" for lab, a, b in zip(labels, ex, ev)))
ex = np.abs(d["x"] - d["ref_x"]).max(axis=1); ev = np.abs(d["v"] - d["ref_v"]).max(axis=1)
print(f"{'fem-dual vs its ref.':24s} all times: x {ex.max():.3e}  v {ev.max():.3e}   (benchmark prints the same)")
print(f"fem-dual error_estimate: {float(d['error_estimate']):.3e}")
np.savez(WORK + "/errors.npz", t=d["t"],
         femdual_x=np.abs(d["x"]-Ex).max(axis=1), femdual_v=np.abs(d["v"]-Ev).max(axis=1),
         expm_x=np.abs(d["ref_x"]-Ex).max(axis=1), expm_v=np.abs(d["ref_v"]-Ev).max(axis=1))
e = np.load(WORK + "/errors.npz")
print("\nerror growth over time (every 64th output time):")
for i in range(0, nt, 64):
    print(f"  t={e['t'][i]:7.3f}  fem-dual x {e['femdual_x'][i]:.2e} v {e['femdual_v'][i]:.2e} | "
          f"reference x {e['expm_x'][i]:.2e} v {e['expm_v'][i]:.2e}")
