"""Accuracy, unlinkability and inversion of every scheme on the LFW test persons.
Usage: python evaluate.py [filter-substring ...]   (results appended to results.jsonl)"""
import json, sys, time
import numpy as np
import protect as P
import attack as A

SEEDS = (1, 2, 3)
OUT = "results.jsonl"

z = np.load("templates.npz")
X, person, sset, split = z["X"], z["person"], z["set"], z["split"]
lab = np.char.add(np.char.add(sset, ":"), person)


def subset(mask):
    return X[mask], lab[mask]


Xt, Lt = subset((sset == "lfw") & (split == "test"))
Xc, Lc = subset((sset == "lfw") & (split == "calibration"))
Xtr, _ = subset((sset == "lfw") & (split == "train"))
parts_t, parts_c = P.split_members(Xt), P.split_members(Xc)
prior = A.Prior(P.split_members(Xtr)) if len(Xtr) > 300 else None
I, J, GEN = P.pairs(Lt)

plain_S = Xt @ Xt.T
plain_gen, plain_imp = plain_S[I, J][GEN], plain_S[I, J][~GEN]
THR = P.thr_at_fmr(plain_imp)
THR_C = THR


def attacked(L):
    cnt = {}
    for l in L: cnt[l] = cnt.get(l, 0) + 1
    return np.array([i for i, l in enumerate(L) if cnt[l] >= 2])


ATT_T = attacked(Lt)
rng = np.random.default_rng(7)
ATT_C = attacked(Lc)
ATT_C = np.sort(rng.choice(ATT_C, min(100, len(ATT_C)), replace=False))
# refinement attacks (costly for large IoM) run on a fixed random subset of the attacked test templates
ATT_TS = np.sort(rng.choice(ATT_T, min(400, len(ATT_T)), replace=False))

# unlinkability pairs (ordered, i != j)
n = len(Lt)
II, JJ = np.nonzero(~np.eye(n, dtype=bool))
MATED = Lt[II] == Lt[JJ]
nm_idx = np.nonzero(~MATED)[0]
nm_idx = np.sort(rng.choice(nm_idx, min(400000, len(nm_idx)), replace=False))


def dsys(SAB):
    m, nm = SAB[II[MATED], JJ[MATED]], SAB[II[nm_idx], JJ[nm_idx]]
    return P.dsys_hist(m, nm), P.dsys_kde(m, nm)


def schemes():
    yield P.Plain()
    yield P.Rotation()
    for m in (16, 32, 64, 128, 256, 512, 1024):
        yield P.BioHash(m, "cos")
    for m in (128, 512):
        yield P.BioHash(m, "ham")
    for m in (2048, 4096):
        yield P.BioHash(m, "cos")
    for m in (256, 512, 1024):
        for q in (2, 4, 8, 16):
            yield P.IoM(m, q)
    for m, q in ((16, 16), (32, 16), (64, 16), (64, 4)):
        yield P.IoM(m, q)
    for k in (8, 16, 32, 64):
        yield P.TopK(128, k)
    for k in (64, 128):
        yield P.TopK(512, k)
    for b in (2, 3, 4):
        yield P.RotQuant(b)


def run(s):
    t0 = time.time()
    r = {"scheme": s.name, "bytes": s.bytes()}
    eers, fnmrs = [], []
    encs = {}
    for seed in SEEDS:
        T = s.enc(parts_t, seed)
        encs[seed] = T
        S = s.score(T, T)
        g, im = S[I, J][GEN], S[I, J][~GEN]
        eers.append(P.eer(g, im)); fnmrs.append(P.fnmr_at(g, im)[0])
        if isinstance(s, P.Plain) and not isinstance(s, P.Rotation):
            break
    r.update(eer=float(np.mean(eers)), eer_sd=float(np.std(eers)), fnmr3=float(np.mean(fnmrs)), fnmr3_sd=float(np.std(fnmrs)),
             eer_seeds=[float(e) for e in eers], fnmr3_seeds=[float(f) for f in fnmrs])
    # unlinkability: secret 1 vs secret 2 (plain: the same templates in two deployments)
    T1 = encs[1]
    T2 = encs.get(2, T1)
    r["dsys_cross_hist"], r["dsys_cross_kde"] = dsys(s.score(T1, T2))
    r["dsys_same_hist"], r["dsys_same_kde"] = dsys(s.score(T1, T1))
    # inversion with secret 1 and one protected template
    refinable = isinstance(s, (P.BioHash, P.IoM, P.TopK))
    configs = [dict(refine=False)]
    if refinable:
        configs += [dict(refine=True, tfrac=0.05, lam=lam, iters=100) for lam in (0.0, 0.3, 3.0)]
    tc = [t[ATT_C] for t in s.enc(parts_c, 11)]
    best, tune = None, []
    for cfg in configs:
        xh = A.invert(s, tc, 11, prior=prior, **cfg) if len(configs) > 1 else None
        if xh is None:
            break
        mr = A.match_rates(xh, Xc, Lc, ATT_C, THR_C)
        tune.append(dict(cfg, attempts=mr[0], templates=mr[1], cos=mr[3]))
        if best is None or mr[0] > best[1]:
            best = (cfg, mr[0])
    cfg = best[0] if best else configs[0]
    att = ATT_TS if refinable else ATT_T
    xh = A.invert(s, [t[att] for t in T1], 1, prior=prior, **cfg)
    mr = A.match_rates(xh, Xt, Lt, att, THR)
    r.update(inv_n=len(att), inv_attempts=mr[0], inv_templates=mr[1], inv_impostor_rate=mr[2], inv_cos=mr[3], inv_cfg=cfg, inv_tuning=tune)
    # the same attack without refinement (classic pre-image), for comparison
    if refinable:
        xh0 = A.invert(s, [t[ATT_T] for t in T1], 1, refine=False)
        mr0 = A.match_rates(xh0, Xt, Lt, ATT_T, THR)
        r.update(inv0_attempts=mr0[0], inv0_templates=mr0[1], inv0_cos=mr0[3])
    r["secs"] = time.time() - t0
    return r


if __name__ == "__main__":
    filt = sys.argv[1:]
    print(f"LFW test: {len(Xt)} templates, {len(set(Lt))} persons, genuine pairs {GEN.sum()}, impostor pairs {(~GEN).sum()}; "
          f"attacked templates {len(ATT_T)}; calib attack subset {len(ATT_C)}; plain thr@1e-3 {THR:.4f}", flush=True)
    done = set()
    try:
        done = {json.loads(l)["scheme"] for l in open(OUT)}
    except FileNotFoundError:
        pass
    for s in schemes():
        if "noise floor" not in done and not filt:
            # D<->sys of two samples from the same (non-mated) distribution, mated-sized: the estimator's floor
            S = Xt @ Xt.T
            nm = S[II[nm_idx], JJ[nm_idx]]
            a = rng.choice(nm, int(MATED.sum()), replace=False)
            r = {"scheme": "noise floor", "dsys_hist": P.dsys_hist(a, nm), "dsys_kde": P.dsys_kde(a, nm), "n_mated": int(MATED.sum()), "n_nonmated": len(nm)}
            open(OUT, "a").write(json.dumps(r) + "\n"); done.add("noise floor"); print(r, flush=True)
        if s.name in done or (filt and not any(f in s.name for f in filt)):
            continue
        r = run(s)
        with open(OUT, "a") as f:
            f.write(json.dumps(r) + "\n")
        print(f"{r['scheme']:40s} EER {100*r['eer']:.3f}% FNMR@1e-3 {100*r['fnmr3']:.3f}% Dx {r['dsys_cross_hist']:.3f}/{r['dsys_cross_kde']:.3f} "
              f"Dsame {r['dsys_same_hist']:.3f} inv {100*r['inv_attempts']:.1f}%/{100*r['inv_templates']:.1f}% cos {r['inv_cos']:.3f} "
              f"{r['bytes']}B {r['secs']:.0f}s", flush=True)
