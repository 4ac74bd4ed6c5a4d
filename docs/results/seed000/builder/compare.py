"""Before/after table of two `jaxnc run mecanum` results.json files (95 % intervals)."""
import json, math, sys
b, a = (json.load(open(p))["results"] for p in sys.argv[1:3])
def ci(s, scale=1.0, d=2):
    m = float(s["mean"])
    if math.isinf(m) or s.get("ci95") is None: return "∞" if math.isinf(m) else f"{scale*m:.{d}f}"
    return f"{scale*m:.{d}f} ± {scale*float(s['ci95']):.{d}f}"
def uf(x, n):
    h = 1.96 * math.sqrt(max(x * (1 - x), 0.25 / n) / n)   # Wald, floored at one event
    return f"{100*x:.1f} ± {100*h:.1f}"
print("| case | J1 abs (cm) before | after | J2 abs (cm) before | after | J3 (s) before | after | J4 before | after | unstable % before | after |")
print("|---|---|---|---|---|---|---|---|---|---|---|")
for c in b:
    B, A = b[c], a[c]; n = B["absolute"]["J1"]["n"]
    print(f"| {c} | {ci(B['absolute']['J1'],100)} | {ci(A['absolute']['J1'],100)} | {ci(B['absolute']['J2'],100)} | {ci(A['absolute']['J2'],100)} "
          f"| {ci(B['absolute']['J3'],1,2)} | {ci(A['absolute']['J3'],1,2)} | {ci(B['J4'],1,4)} | {ci(A['J4'],1,4)} "
          f"| {uf(B['unstable_fraction'], n)} | {uf(A['unstable_fraction'], n)} |")
