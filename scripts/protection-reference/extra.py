"""Finalists: (a) D<->sys cross-secret over several secret pairs; (b) accuracy on a larger pair set
(LFW test + calibration persons) and on IMM+ORL held-out persons. -> extra.json"""
import json
import numpy as np
import protect as P
import evaluate as E

fin = [P.Plain(), P.Rotation(), P.RotQuant(3), P.RotQuant(4), P.BioHash(1024), P.BioHash(2048), P.BioHash(4096), P.TopK(128, 8)]
res = {}
for s in fin:
    r = {}
    d = []
    for a, b in ((1, 2), (3, 4), (5, 6), (7, 8)):
        d.append(E.dsys(s.score(s.enc(E.parts_t, a), s.enc(E.parts_t, b))))
    r["dsys_cross_pairs"] = d
    for name, mask in (("lfw test+calibration", (E.sset == "lfw") & (E.split != "train")),
                       ("imm+orl held-out", (E.sset != "lfw") & (E.split == "test"))):
        X, L = E.X[mask], E.lab[mask]
        parts = P.split_members(X)
        I, J, G = P.pairs(L)
        out = []
        for seed in ((1,) if type(s) is P.Plain else (1, 2, 3)):
            S = s.score(*(2 * [s.enc(parts, seed)]))
            g, im = S[I, J][G], S[I, J][~G]
            out.append((P.eer(g, im), P.fnmr_at(g, im)[0]))
        r[name] = dict(n_gen=int(G.sum()), n_imp=int((~G).sum()), eer=float(np.mean([o[0] for o in out])), fnmr3=float(np.mean([o[1] for o in out])))
    res[s.name] = r
    print(s.name, json.dumps(r), flush=True)
json.dump(res, open("extra.json", "w"), indent=1)
