"""Inversion attacks: the attacker knows the secret (seed) and holds ONE protected template; it
outputs an estimate of the member embeddings, re-fused and unit-normalised. The attacker also has
public face data (LFW training persons through the same public networks) for a prior.

Linear / orthogonal schemes: exact inverse (transpose).
Sign, IoM and top-k codes: every code is a set of linear inequalities on the embedding (a cell);
the attack starts from the classic back-projection pre-image and then runs projected Adam on
the unit sphere, minimising mean softplus(-margin / T) over the cell's constraints (a smooth
analytic-centre of the cell) plus optionally lambda * a Gaussian prior from public embeddings."""
import numpy as np
import protect as P


def unit(x):
    return x / np.linalg.norm(x, axis=1, keepdims=True)


class Prior:
    def __init__(self, parts_public, ridge=1e-3):
        self.mu, self.prec = [], []
        for p in parts_public:
            mu = p.mean(0)
            c = np.cov(p.T) + ridge * np.eye(p.shape[1])
            self.mu.append(mu)
            self.prec.append(np.linalg.inv(c))

    def grad(self, k, X):
        d = X - self.mu[k]
        return d @ self.prec[k] / X.shape[1]


def sphere_adam(X0, grad_fn, iters=200, lr=0.01):
    X = unit(X0.astype(np.float32))
    m = np.zeros_like(X); v = np.zeros_like(X)
    b1, b2, eps = 0.9, 0.999, 1e-8
    for t in range(1, iters + 1):
        G = grad_fn(X)
        G = G - np.sum(G * X, 1, keepdims=True) * X  # tangent
        m = b1 * m + (1 - b1) * G
        v = b2 * v + (1 - b2) * G * G
        step = lr * (1 - (t - 1) / iters) * (m / (1 - b1 ** t)) / (np.sqrt(v / (1 - b2 ** t)) + eps)
        X = unit(X - step)
    return X


def sig(z):
    return 0.5 * (1 + np.tanh(0.5 * z))


def dloss(M, Tm, loss, tfrac):
    """d loss / d margin. softplus: smooth cell centre (keeps pushing margins up);
    hinge: squared hinge that is zero once a constraint holds with a small margin, so that inside
    the cell only the prior acts (a MAP estimate under the public-data Gaussian prior)."""
    if loss == "softplus":
        return -sig(-M / Tm) / Tm
    s0 = Tm / tfrac
    return -2 * np.maximum(0.05 * s0 - M, 0) / (s0 * s0)


def invert(scheme, T_list, seed, prior=None, lam=0.0, tfrac=0.1, iters=200, refine=True, loss="softplus"):
    """Member estimates for each protected template (list per member) -> fused unit vectors."""
    keys = scheme.keys(seed)
    if keys is None:
        return P.fuse([t.astype(np.float64) for t in T_list])
    est = []
    for k, (T, K) in enumerate(zip(T_list, keys)):
        if isinstance(scheme, P.Plain) and K is None:
            est.append(T.astype(np.float64)); continue
        if isinstance(scheme, P.Rotation):
            est.append(T @ K); continue
        if isinstance(scheme, P.RotQuant):
            est.append(T @ K); continue  # dequantised levels rotated back: centre of the cell
        pg = (lambda X, k=k: lam * prior.grad(k, X)) if (prior is not None and lam > 0) else (lambda X: 0)
        if isinstance(scheme, P.BioHash):
            B = T.astype(np.float32)
            Rn = (K / np.linalg.norm(K, axis=1, keepdims=True)).astype(np.float32)
            X0 = B @ Rn
            if refine:
                Tm = tfrac * np.median(np.abs(unit(X0) @ Rn.T))

                def g(X):
                    M = B * (X @ Rn.T)
                    G = dloss(M, Tm, loss, tfrac) * B / B.shape[1]
                    return G @ Rn + pg(X)
                X0 = sphere_adam(X0, g, iters)
            est.append(unit(X0))
        elif isinstance(scheme, P.IoM):
            W = K.astype(np.float32)  # m, q, d
            m, q, d = W.shape
            c = T.astype(np.int64)
            Wc = W[np.arange(m)[None, :], c]  # N, m, d (winners)
            X0 = (Wc - W.mean(1)[None]).sum(1)
            if refine:
                Wf = W.reshape(m * q, d)
                onehot = np.zeros((T.shape[0], m, q), bool)
                np.put_along_axis(onehot, c[..., None], True, 2)
                Pp = (unit(X0) @ Wf.T).reshape(-1, m, q)
                win = np.take_along_axis(Pp, c[..., None], 2)
                Tm = tfrac * np.median(np.abs(win - Pp)[~onehot])
                del Pp, win

                def g(X):
                    Pp = (X @ Wf.T).reshape(-1, m, q)
                    win = np.take_along_axis(Pp, c[..., None], 2)
                    G = dloss(win - Pp, Tm, loss, tfrac) / (m * (q - 1))
                    G[onehot] = 0
                    dP = -G
                    dP[onehot] = G.sum(2).ravel()
                    return dP.reshape(-1, m * q) @ Wf + pg(X)
                X0 = sphere_adam(X0, g, iters)
            est.append(unit(X0))
        elif isinstance(scheme, P.TopK):
            R = K.astype(np.float32)
            S = T != 0
            s = T.astype(np.float32)
            X0 = s @ R
            if refine:
                y0 = unit(X0) @ R.T
                Tm = tfrac * np.median(np.abs(y0))

                def g(X):
                    y = X @ R.T
                    a = np.where(S, s * y, np.inf).min(1, keepdims=True)
                    b = np.where(S, -np.inf, np.abs(y)).max(1, keepdims=True)
                    tau = (a + b) / 2
                    M = np.where(S, s * y - tau, tau - np.abs(y))
                    G = dloss(M, Tm, loss, tfrac) / R.shape[0]
                    dy = np.where(S, G * s, -G * np.sign(y))
                    return dy @ R + pg(X)
                X0 = sphere_adam(X0, g, iters)
            est.append(unit(X0))
        else:
            raise ValueError(scheme)
    return P.fuse(est)


def match_rates(Xhat, Xplain, labels, idx_attacked, thr):
    """For each attacked template i (of a person with other photos): scores of the recovered
    vector against the plain templates of the person's OTHER photos; match if > thr.
    Returns (fraction of attempts, fraction of templates matching >= 1 other photo,
    impostor match rate of recovered vectors, mean cosine to the original template)."""
    S = Xhat @ Xplain.T
    att, anyp, imp_hits, imp_n, cos = 0, 0, 0, 0, []
    hits = 0
    for r, i in enumerate(idx_attacked):
        same = (labels == labels[i]); same[i] = False
        sc = S[r, same]
        hits += np.sum(sc > thr); att += len(sc); anyp += np.any(sc > thr)
        diff = labels != labels[i]
        imp_hits += np.sum(S[r, diff] > thr); imp_n += diff.sum()
        cos.append(Xhat[r] @ Xplain[i])
    return hits / att, anyp / len(idx_attacked), imp_hits / imp_n, float(np.mean(cos))
