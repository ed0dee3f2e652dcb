"""results.jsonl -> markdown table (table.md)."""
import json
rows, seen = [], set()
for l in open("results.jsonl"):
    r = json.loads(l)
    if r["scheme"] not in seen:
        seen.add(r["scheme"]); rows.append(r)
gibbs = {}
try:
    for l in open("results_gibbs.jsonl"):
        g = json.loads(l); gibbs[g["scheme"]] = g
except FileNotFoundError:
    pass
fam = ["plain", "keyed", "BioHash", "IoM", "rotate+top", "project+top", "rotate+"]
rows.sort(key=lambda r: (next(i for i, f in enumerate(fam) if r["scheme"].startswith(f)) if r["scheme"] != "noise floor" else -1,
                         "(ham)" in r["scheme"], r.get("bytes", 0), r["scheme"]))
for r in rows:
    g = gibbs.get(r["scheme"])
    if g and g["inv_attempts"] > r.get("inv_attempts", 0):
        r.update(inv_attempts=g["inv_attempts"], inv_templates=g["inv_templates"], inv_cos=g["inv_cos"], inv_cfg={"refine": "gibbs"})
floor = next((r for r in rows if r["scheme"] == "noise floor"), None)
plain = next(r for r in rows if r["scheme"] == "plain fusion")
out = []
if floor:
    out.append(f"D<->sys estimator floor (two samples of the same non-mated distribution, {floor['n_mated']} vs {floor['n_nonmated']}): "
               f"histogram {floor['dsys_hist']:.3f}, KDE {floor['dsys_kde']:.3f}\n")
out.append("| scheme | bytes | EER % (±sd, 3 secrets) | ΔEER pp | FNMR@FMR1e-3 % (±sd) | ΔFNMR pp | D↔sys cross-secret hist / KDE | D↔sys same-secret | inversion: attempts % / templates ≥1 % (cos to original) | classic pre-image attempts % | attack |")
out.append("|---|---|---|---|---|---|---|---|---|---|---|")
for r in rows:
    if r["scheme"] == "noise floor":
        continue
    cfg = r.get("inv_cfg", {})
    att = "exact inverse / back-projection" if not cfg.get("refine") else ("Gibbs posterior mean (prior)" if cfg["refine"] == "gibbs" else f"cell-centre refine, prior λ={cfg['lam']}")
    inv0 = f"{100*r['inv0_attempts']:.1f}" if "inv0_attempts" in r else "—"
    out.append(f"| {r['scheme']} | {r['bytes']} | {100*r['eer']:.3f} ± {100*r['eer_sd']:.3f} | {100*(r['eer']-plain['eer']):+.3f} | "
               f"{100*r['fnmr3']:.3f} ± {100*r['fnmr3_sd']:.3f} | {100*(r['fnmr3']-plain['fnmr3']):+.3f} | "
               f"{r['dsys_cross_hist']:.3f} / {r['dsys_cross_kde']:.3f} | {r['dsys_same_hist']:.3f} | "
               f"{100*r['inv_attempts']:.1f} / {100*r['inv_templates']:.1f} ({r['inv_cos']:.3f}) | {inv0} | {att} |")
open("table.md", "w").write("\n".join(out) + "\n")
print("\n".join(out))
