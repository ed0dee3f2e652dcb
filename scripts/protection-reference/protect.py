"""Template-protection schemes over facegate's fusion templates, their scores, metrics and
inversion attacks (numpy). The fused template is [sqrt(0.8) * dlib_unit (128), sqrt(0.2) * sface_unit (128)]
(crates/vision/src/recognize/embedding.rs `fuse`, models/fusion.bin weights 0.8 / 0.2)."""
import os
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
import zlib
import numpy as np

WEIGHTS = (0.8, 0.2)
DIMS = ((0, 128), (128, 256))
D = 128


def split_members(X):
    """Fused templates -> list of unit member embeddings."""
    out = []
    for a, b in DIMS:
        e = X[:, a:b]
        out.append(e / np.linalg.norm(e, axis=1, keepdims=True))
    return out


def fuse(parts):
    return np.hstack([np.sqrt(w) * p / np.linalg.norm(p, axis=1, keepdims=True) for w, p in zip(WEIGHTS, parts)])


def rng_for(seed, member, tag):
    return np.random.default_rng([int(seed), member, zlib.crc32(tag.encode())])


def orthogonal(rng, d):
    q, r = np.linalg.qr(rng.standard_normal((d, d)))
    return q * np.sign(np.diag(r))


# Lloyd-Max reconstruction levels / thresholds for N(0,1)
LLOYD = {
    2: (np.array([-1.5104, -0.4528, 0.4528, 1.5104]), np.array([-0.9816, 0.0, 0.9816])),
    3: (np.array([-2.1520, -1.3439, -0.7560, -0.2451, 0.2451, 0.7560, 1.3439, 2.1520]),
        np.array([-1.7479, -1.0500, -0.5006, 0.0, 0.5006, 1.0500, 1.7479])),
}
_l4 = np.array([0.1284, 0.3881, 0.6568, 0.9424, 1.2562, 1.6180, 2.0690, 2.7326])
_l4 = np.concatenate([-_l4[::-1], _l4])
LLOYD[4] = (_l4, np.concatenate([[(a + b) / 2 for a, b in zip(_l4[:-1], _l4[1:])]]))


class Scheme:
    """enc(parts, seed) -> protected template (list per member); score(TA, TB) -> fused score matrix."""
    name = "?"

    def bytes(self):
        raise NotImplementedError


class Plain(Scheme):
    def __init__(self):
        self.name = "plain fusion"

    def keys(self, seed):
        return None

    def enc(self, parts, seed):
        return [p.astype(np.float32) for p in parts]

    def score(self, A, B):
        return sum(w * (a @ b.T) for w, a, b in zip(WEIGHTS, A, B))

    def bytes(self):
        return 256 * 4


class Rotation(Plain):
    def __init__(self):
        self.name = "keyed orthogonal rotation"

    def keys(self, seed):
        return [orthogonal(rng_for(seed, k, "rot"), D) for k in range(2)]

    def enc(self, parts, seed):
        return [(p @ q.T).astype(np.float32) for p, q in zip(parts, self.keys(seed))]


class BioHash(Scheme):
    """sign(R e), R Gaussian m x d per member. fusion 'ham': sum w (1 - h); 'cos': sum w cos(pi h)."""

    def __init__(self, m, fusion="cos"):
        self.m, self.fusion = m, fusion
        self.name = f"BioHash m={m} ({fusion})"

    def keys(self, seed):
        return [rng_for(seed, k, f"bh{self.m}").standard_normal((self.m, D)) for k in range(2)]

    def enc(self, parts, seed):
        return [np.where(p @ R.T >= 0, 1, -1).astype(np.float32) for p, R in zip(parts, self.keys(seed))]

    def score(self, A, B):
        s = 0
        for w, a, b in zip(WEIGHTS, A, B):
            h = (self.m - a @ b.T) / (2 * self.m)  # normalised Hamming distance
            s = s + w * (np.cos(np.pi * h) if self.fusion == "cos" else 1 - h)
        return s

    def bytes(self):
        return 2 * self.m // 8


class IoM(Scheme):
    """Index-of-Max, Gaussian random projection (Jin et al. 2018): m hashes, each argmax of q projections."""

    def __init__(self, m, q):
        self.m, self.q = m, q
        self.name = f"IoM-GRP m={m} q={q}"

    def keys(self, seed):
        return [rng_for(seed, k, f"iom{self.m}_{self.q}").standard_normal((self.m, self.q, D)) for k in range(2)]

    def codes(self, parts, seed):
        return [np.argmax(np.einsum("nd,mqd->nmq", p, W, optimize=True), axis=2).astype(np.int16) for p, W in zip(parts, self.keys(seed))]

    def enc(self, parts, seed):
        return self.codes(parts, seed)

    def onehot(self, c):
        n = c.shape[0]
        o = np.zeros((n, self.m * self.q), np.float32)
        o[np.arange(n)[:, None], np.arange(self.m)[None, :] * self.q + c] = 1
        return o

    def score(self, A, B):
        return sum(w * (self.onehot(a) @ self.onehot(b).T) / self.m for w, a, b in zip(WEIGHTS, A, B))

    def bytes(self):
        return int(np.ceil(2 * self.m * np.log2(self.q) / 8))


class TopK(Scheme):
    """Keyed projection (orthogonal rotation if n == 128, else Gaussian n x d), then only the k
    largest-magnitude coordinates' indices and signs (a sparse ternary vector); score = overlap / k."""

    def __init__(self, n, k):
        self.n, self.k = n, k
        self.name = f"rotate+top-k sign n={n} k={k}" if n == D else f"project+top-k sign n={n} k={k}"

    def keys(self, seed):
        if self.n == D:
            return [orthogonal(rng_for(seed, k, "topk"), D) for k in range(2)]
        return [rng_for(seed, k, f"topk{self.n}").standard_normal((self.n, D)) / np.sqrt(D) for k in range(2)]

    def enc(self, parts, seed):
        out = []
        for p, R in zip(parts, self.keys(seed)):
            y = p @ R.T
            idx = np.argsort(-np.abs(y), axis=1)[:, :self.k]
            t = np.zeros_like(y, dtype=np.float32)
            np.put_along_axis(t, idx, np.sign(np.take_along_axis(y, idx, 1)), 1)
            out.append(t)
        return out

    def score(self, A, B):
        return sum(w * (a @ b.T) / self.k for w, a, b in zip(WEIGHTS, A, B))

    def bytes(self):
        return int(np.ceil(2 * self.k * (np.log2(self.n) + 1) / 8))


class RotQuant(Scheme):
    """Keyed rotation, then each coordinate quantised to b bits (Lloyd-Max for N(0,1/d)); score = cosine of dequantised."""

    def __init__(self, bits):
        self.b = bits
        self.name = f"rotate+{bits}-bit quantisation"

    def keys(self, seed):
        return [orthogonal(rng_for(seed, k, "rq"), D) for k in range(2)]

    def levels(self, y):
        lv, th = LLOYD[self.b]
        return np.searchsorted(th, y * np.sqrt(D))

    def enc(self, parts, seed):
        lv, _ = LLOYD[self.b]
        out = []
        for p, Q in zip(parts, self.keys(seed)):
            v = lv[self.levels(p @ Q.T)]
            out.append((v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32))
        return out

    def score(self, A, B):
        return sum(w * (a @ b.T) for w, a, b in zip(WEIGHTS, A, B))

    def bytes(self):
        return 2 * D * self.b // 8


# ---------------------------------------------------------------- metrics

def pairs(labels):
    """Upper-triangle index pairs and genuine mask."""
    n = len(labels)
    i, j = np.triu_indices(n, 1)
    return i, j, labels[i] == labels[j]


def thr_at_fmr(imp, fmr=1e-3):
    """Accept if score > t; FMR = #(imp > t)/n <= fmr."""
    s = np.sort(imp)[::-1]
    k = int(np.floor(fmr * len(s)))
    return s[k]


def fnmr_at(gen, imp, fmr=1e-3):
    t = thr_at_fmr(imp, fmr)
    return np.mean(gen <= t), np.mean(imp > t), t


def eer(gen, imp):
    thr = np.unique(np.concatenate([gen, imp]))
    gs, is_ = np.sort(gen), np.sort(imp)
    # accept if score >= t
    fnmr = np.searchsorted(gs, thr, side="left") / len(gs)
    fmr = 1 - np.searchsorted(is_, thr, side="left") / len(is_)
    k = np.argmin(np.abs(fnmr - fmr))
    # interpolate between neighbouring thresholds
    best = (fnmr[k] + fmr[k]) / 2
    for kk in (k - 1, k):
        if 0 <= kk < len(thr) - 1:
            a1, b1, a2, b2 = fnmr[kk], fmr[kk], fnmr[kk + 1], fmr[kk + 1]
            d1, d2 = a1 - b1, a2 - b2
            if d1 <= 0 <= d2 and d2 != d1:
                t = -d1 / (d2 - d1)
                best = a1 + t * (a2 - a1)
    return best


def dsys_hist(mated, nonmated, bins=100, omega=1.0):
    """Gomez-Barrero et al. (TIFS 2018) D<->sys with histogram densities on a common range."""
    lo, hi = min(mated.min(), nonmated.min()), max(mated.max(), nonmated.max())
    if hi <= lo:
        return 0.0
    edges = np.linspace(lo, hi + 1e-12, bins + 1)
    pm = np.histogram(mated, edges)[0] / len(mated)
    pn = np.histogram(nonmated, edges)[0] / len(nonmated)
    with np.errstate(divide="ignore", invalid="ignore"):
        lr = np.where(pn > 0, pm / np.where(pn > 0, pn, 1), np.inf)
        d = np.where(omega * lr <= 1, 0.0, np.where(np.isinf(lr), 1.0, 2 * omega * lr / (1 + omega * lr) - 1))
    return float(np.sum(pm * d))


def dsys_kde(mated, nonmated, omega=1.0, grid=1024, max_n=40000, seed=0):
    """Same with Gaussian KDE densities (Scott bandwidth), integrated on a grid."""
    from scipy.stats import gaussian_kde
    r = np.random.default_rng(seed)
    m = mated if len(mated) <= max_n else r.choice(mated, max_n, replace=False)
    n = nonmated if len(nonmated) <= max_n else r.choice(nonmated, max_n, replace=False)
    if np.ptp(np.concatenate([m, n])) == 0:
        return 0.0
    # discrete scores: jitter by a fraction of the smallest step so the KDE is defined
    km, kn = gaussian_kde(m + 1e-9 * r.standard_normal(len(m))), gaussian_kde(n + 1e-9 * r.standard_normal(len(n)))
    lo, hi = min(m.min(), n.min()), max(m.max(), n.max())
    pad = 0.1 * (hi - lo)
    s = np.linspace(lo - pad, hi + pad, grid)
    pm, pn = km(s), kn(s)
    lr = pm / np.maximum(pn, 1e-300)
    d = np.where(omega * lr <= 1, 0.0, 2 * omega * lr / (1 + omega * lr) - 1)
    return float(np.trapezoid(pm * d, s))
