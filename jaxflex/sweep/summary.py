"""Fixed-size, exactly mergeable summaries of a sweep (host side, numpy).

The ``Accumulator`` folds in one chunk at a time and holds, whatever the number of samples:

- histograms of RMS and max link error [rad] and torque RMS [N m] on a log grid, and of the
  saturation fraction, for quantiles and figures;
- histograms of the link error e1 [rad] at every band time (uniform in asinh(e1 / 1 urad),
  about 8 % relative resolution) for error bands over time;
- sufficient statistics (sums, X^T X, X^T y) of the parameters and the RMS error, for
  sensitivities valid under correlated draws (``shapley_r2``: each parameter's Shapley share
  of the linear R^2, which splits the variance shared by correlated parameters between them
  instead of inflating their regression coefficients) beside the marginal correlation, the
  standardised regression coefficient (SRC) and its variance inflation factor;
- the ``n_worst`` samples of largest RMS error (diverged first) with their parameters;
- optionally each sample's parameters and metrics (``keep_samples``), which add exact
  quantiles and Spearman rank correlations.

Chunks merge by addition (and top-k), so the result does not depend on chunking, sharding or
the number of processes.
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from jaxflex.sweep.spec import SweepSpec

METRICS: tuple[str, ...] = ("rms_error", "max_error", "tau_rms", "saturation_fraction")
QUANTILES: tuple[float, ...] = (0.05, 0.25, 0.5, 0.75, 0.95, 0.99)
BAND_QUANTILES: tuple[float, ...] = (0.05, 0.25, 0.5, 0.75, 0.95)
_LOG_EDGES = np.logspace(-10, 3, 13 * 40 + 1)  # 40 bins per decade, 1e-10 .. 1e3
_LIN_EDGES = np.linspace(0.0, 1.0, 101)


def band_bins() -> np.ndarray:
    """Edges (in asinh(e1 / 1e-6 rad)) of the band histograms: 400 bins over +-10 rad."""
    top = math.asinh(10.0 / 1e-6)
    return np.linspace(-top, top, 401)


def _edges(metric: str) -> np.ndarray:
    return _LIN_EDGES if metric == "saturation_fraction" else _LOG_EDGES


def _hist(metric: str, v: np.ndarray) -> np.ndarray:
    e = _edges(metric)
    idx = np.clip(np.searchsorted(e, v, side="right") - 1, 0, e.size - 2)
    return np.bincount(idx, minlength=e.size - 1).astype(np.int64)


def hist_quantiles(counts: np.ndarray, edges: np.ndarray, qs: tuple[float, ...]) -> np.ndarray:
    """Quantiles from histogram counts (last axis), linear inside a bin; NaN where empty."""
    counts = np.asarray(counts, float)
    cum = np.cumsum(counts, axis=-1)
    tot = cum[..., -1:]
    out = np.full(counts.shape[:-1] + (len(qs),), np.nan)
    flat_c, flat_cum = counts.reshape(-1, counts.shape[-1]), cum.reshape(-1, counts.shape[-1])
    o = out.reshape(-1, len(qs))
    for r in range(flat_c.shape[0]):
        T = flat_cum[r, -1]
        if T <= 0:
            continue
        for j, q in enumerate(qs):
            target = q * T
            b = int(np.searchsorted(flat_cum[r], target, side="left"))
            b = min(b, flat_c.shape[1] - 1)
            prev = flat_cum[r, b - 1] if b > 0 else 0.0
            frac = (target - prev) / flat_c[r, b] if flat_c[r, b] > 0 else 0.5
            o[r, j] = edges[b] + frac * (edges[b + 1] - edges[b])
    del tot
    return out


def _rank(x: np.ndarray) -> np.ndarray:
    order = np.argsort(x, kind="stable")
    r = np.empty(len(x))
    r[order] = np.arange(len(x))
    # average ranks of ties
    xs = x[order]
    i = 0
    while i < len(xs):
        j = i
        while j + 1 < len(xs) and xs[j + 1] == xs[i]:
            j += 1
        if j > i:
            r[order[i:j + 1]] = 0.5 * (i + j)
        i = j + 1
    return r


def spearman(x: np.ndarray, y: np.ndarray) -> float:
    """Spearman rank correlation of two 1-D samples (NaN if either is constant)."""
    rx, ry = _rank(np.asarray(x, float)), _rank(np.asarray(y, float))
    sx, sy = rx.std(), ry.std()
    if sx == 0 or sy == 0:
        return float("nan")
    return float(np.mean((rx - rx.mean()) * (ry - ry.mean())) / (sx * sy))


@dataclasses.dataclass
class SweepResult:
    """Summary of a sweep. ``summary`` is JSON-able; arrays are for figures.

    band_t [s] (T,), band_q [rad] (n, T, len(BAND_QUANTILES)) link-error quantiles over time;
    hists: metric -> (edges, counts); samples: per-sample arrays when kept (theta (S, d) and
    each metric (S,), index (S,)).
    """

    summary: dict[str, Any]
    band_t: np.ndarray
    band_q: np.ndarray
    hists: dict[str, tuple[np.ndarray, np.ndarray]]
    samples: dict[str, np.ndarray] | None = None
    timing: dict[str, Any] = dataclasses.field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """Summary, timing and error bands as one JSON-able mapping."""
        return {
            **self.summary, "timing": self.timing,
            "bands": {"t": self.band_t.tolist(), "quantiles": list(BAND_QUANTILES),
                      "e1": np.where(np.isfinite(self.band_q), self.band_q, None).tolist()},
        }


class Accumulator:
    """Streaming summary of a sweep (see the module docstring)."""

    def __init__(self, spec: SweepSpec, keep_samples: bool = True, n_worst: int = 10) -> None:
        self.spec = spec
        self.keep = keep_samples
        self.n_worst = n_worst
        d = len(spec.columns)
        cs = [c.dist.center_scale() for c in spec.columns]
        self.center = np.array([c for c, _ in cs], float)
        self.scale = np.array([s for _, s in cs], float)
        N = round(spec.t_final / spec.dt)
        self.T = len(range(0, N, spec.band_stride))
        self.band_dt = spec.dt * spec.band_stride
        self.count = 0
        self.diverged = 0
        self.fs_raised = 0
        self.hists = {m: np.zeros(_edges(m).size - 1, np.int64) for m in METRICS}
        self.sums = {m: np.zeros(2) for m in METRICS}  # sum, sum of squares (non-diverged)
        self.band = np.zeros((spec.n, self.T, band_bins().size - 1), np.int64)
        # regression statistics over non-diverged samples: [1, x_std] and y = rms_error
        self.xtx = np.zeros((d + 1, d + 1))
        self.xty = np.zeros(d + 1)
        self.yy = 0.0
        self.worst: dict[str, np.ndarray] = {
            "index": np.zeros(0, np.int64), "score": np.zeros(0), "theta": np.zeros((0, d)),
            **{m: np.zeros(0) for m in METRICS}, "diverged": np.zeros(0, bool),
        }
        self.kept: list[dict[str, np.ndarray]] = []

    def add(self, index: np.ndarray, out: dict[str, np.ndarray]) -> None:
        """Fold in one chunk: ``index`` (S,), per-sample arrays (S, ...) and ``band_hist``."""
        index = np.asarray(index, np.int64)
        div = np.asarray(out["diverged"], bool)
        ok = ~div
        self.count += index.size
        self.diverged += int(div.sum())
        self.fs_raised += int(np.asarray(out["fs_raised"]).sum())
        for m in METRICS:
            v = np.asarray(out[m], float)[ok]
            self.hists[m] += _hist(m, v)
            self.sums[m] += [v.sum(), (v**2).sum()]
        self.band += np.asarray(out["band_hist"], np.int64)
        theta = np.asarray(out["theta"], float).reshape(index.size, -1)
        X = np.column_stack([np.ones(ok.sum()), (theta[ok] - self.center) / self.scale])
        y = np.asarray(out["rms_error"], float)[ok]
        self.xtx += X.T @ X
        self.xty += X.T @ y
        self.yy += float(y @ y)
        score = np.where(div, np.inf, np.asarray(out["rms_error"], float))
        cand = {"index": index, "score": score, "theta": theta, "diverged": div,
                **{m: np.asarray(out[m], float) for m in METRICS}}
        self._merge_worst(cand)
        if self.keep:
            self.kept.append({"index": index, "theta": theta, "diverged": div,
                              **{m: np.asarray(out[m], float) for m in METRICS}})

    def _merge_worst(self, cand: dict[str, np.ndarray]) -> None:
        both = {k: np.concatenate([self.worst[k], cand[k]]) for k in self.worst}
        # largest score first, ties by sample index so the order is reproducible
        order = np.lexsort((both["index"], -np.nan_to_num(both["score"], nan=np.inf)))[: self.n_worst]
        self.worst = {k: v[order] for k, v in both.items()}

    def merge(self, other: Accumulator) -> None:
        """Add another accumulator of the same spec (other chunks)."""
        self.count += other.count
        self.diverged += other.diverged
        self.fs_raised += other.fs_raised
        for m in METRICS:
            self.hists[m] += other.hists[m]
            self.sums[m] += other.sums[m]
        self.band += other.band
        self.xtx += other.xtx
        self.xty += other.xty
        self.yy += other.yy
        self._merge_worst(other.worst)
        self.kept += other.kept

    def _pack(self) -> dict[str, np.ndarray]:
        d = {"scalars": np.array([self.count, self.diverged, self.fs_raised, self.yy], float),
             "band": self.band, "xtx": self.xtx, "xty": self.xty}
        for m in METRICS:
            d[f"h_{m}"] = self.hists[m]
            d[f"s_{m}"] = self.sums[m]
        # worst, padded to n_worst rows (score -inf marks padding)
        k = self.n_worst
        pad = k - self.worst["index"].size
        for key, v in self.worst.items():
            fill = -np.inf if key == "score" else 0
            shape = (pad,) + v.shape[1:]
            d[f"w_{key}"] = np.concatenate([v.astype(float), np.full(shape, fill)])
        return d

    def allgather(self) -> Accumulator:
        """Combine the accumulators of all ``jax.distributed`` processes (every process gets
        the total). Kept samples are gathered too, padded to the largest share."""
        from jax.experimental import multihost_utils as mu

        mine = self._pack()
        allp = {k: np.asarray(mu.process_allgather(v)) for k, v in mine.items()}
        P = allp["scalars"].shape[0]
        tot = Accumulator(self.spec, keep_samples=False, n_worst=self.n_worst)
        for p in range(P):
            a = Accumulator(self.spec, keep_samples=False, n_worst=self.n_worst)
            c, dv, fs, yy = allp["scalars"][p]
            a.count, a.diverged, a.fs_raised, a.yy = int(c), int(dv), int(fs), float(yy)
            a.band, a.xtx, a.xty = allp["band"][p].astype(np.int64), allp["xtx"][p], allp["xty"][p]
            for m in METRICS:
                a.hists[m] = allp[f"h_{m}"][p].astype(np.int64)
                a.sums[m] = allp[f"s_{m}"][p]
            real = allp["w_score"][p] > -np.inf
            a.worst = {k: allp[f"w_{k}"][p][real] for k in self.worst}
            a.worst["index"] = a.worst["index"].astype(np.int64)
            a.worst["diverged"] = a.worst["diverged"].astype(bool)
            tot.merge(a)
        if self.keep:
            tot.keep = True
            tot.kept = [_gather_samples(self.kept)]
        return tot

    def result(self) -> SweepResult:
        """The summary: quantiles, worst cases, sensitivities, bands, histograms."""
        spec, labels = self.spec, self.spec.labels
        ok = self.count - self.diverged
        samples = None
        if self.keep and self.kept:
            samples = {k: np.concatenate([c[k] for c in self.kept]) for c in self.kept[:1] for k in c}
            order = np.argsort(samples["index"], kind="stable")
            samples = {k: v[order] for k, v in samples.items()}
        metrics: dict[str, Any] = {}
        for m in METRICS:
            s, s2 = self.sums[m]
            mean = s / ok if ok else float("nan")
            std = math.sqrt(max(s2 / ok - mean**2, 0.0)) if ok else float("nan")
            if samples is not None and ok:
                v = samples[m][~samples["diverged"]]
                qv, how = np.quantile(v, QUANTILES), "exact"
                mx = float(v.max())
            else:
                qv, how = hist_quantiles(self.hists[m], _edges(m), QUANTILES), "histogram"
                nz = np.nonzero(self.hists[m])[0]
                mx = float(_edges(m)[nz[-1] + 1]) if nz.size else float("nan")
            metrics[m] = {"mean": mean, "std": std, "max": mx, "quantiles_from": how,
                          **{f"q{round(q * 100):02d}": float(x) for q, x in zip(QUANTILES, qv)}}
        sens = self._sensitivity(samples)
        worst = []
        for r in range(self.worst["index"].size):
            worst.append({
                "index": int(self.worst["index"][r]), "diverged": bool(self.worst["diverged"][r]),
                **{m: float(self.worst[m][r]) for m in METRICS},
                "parameters": {lab: float(v) for lab, v in zip(labels, self.worst["theta"][r])},
            })
        summary = {
            "spec": spec.to_dict(), "samples": self.count, "diverged": self.diverged,
            "diverged_fraction": self.diverged / max(self.count, 1), "fs_raised_to_fc": self.fs_raised,
            "metrics": metrics, "sensitivity": sens, "worst": worst,
            "sensitivity_warnings": [collinear_warning(g) for g in collinear_groups(sens)],
        }
        edges = band_bins()
        bq = hist_quantiles(self.band, edges, BAND_QUANTILES)
        bq = np.sinh(bq) * 1e-6
        return SweepResult(
            summary=summary, band_t=np.arange(self.T) * self.band_dt, band_q=bq,
            hists={m: (_edges(m), self.hists[m].copy()) for m in METRICS}, samples=samples,
        )

    def _sensitivity(self, samples: dict[str, np.ndarray] | None) -> list[dict[str, Any]]:
        """Per sampled parameter, its effect on the RMS error (``sensitivities``; with kept
        samples also Spearman's rank correlation); sorted by Shapley share, largest first."""
        labels = self.spec.labels
        n = self.xtx[0, 0]
        d = len(labels)
        if d == 0 or n < d + 2:
            return []
        mean_x = self.xtx[0, 1:] / n
        cov = self.xtx[1:, 1:] / n - np.outer(mean_x, mean_x)
        mean_y = self.xty[0] / n
        cxy = self.xty[1:] / n - mean_x * mean_y
        var_y = self.yy / n - mean_y**2
        rows = sensitivities(cov, cxy, var_y, labels)
        if samples is not None:
            okm = ~samples["diverged"]
            y = samples["rms_error"][okm]
            rho = {labels[j]: spearman(samples["theta"][okm, j], y) for j in range(d)}
            for r in rows:
                r["spearman"] = rho[r["parameter"]]
        return rows


#: Variance inflation factor above which a parameter's regression coefficient (SRC) is not
#: separable from those of the parameters it is drawn correlated with (a common rule: 10).
VIF_LIMIT: float = 10.0
#: Exact Shapley shares up to this many parameters (2^d subsets), sampled permutations above.
SHAPLEY_EXACT_MAX: int = 12


def _r2(corr: np.ndarray, r: np.ndarray, subset: np.ndarray) -> float:
    """Linear R^2 of y on the parameters ``subset`` from their correlation matrix ``corr``
    and their correlations ``r`` with y (pseudo-inverse: collinear sets are fine)."""
    if not subset.any():
        return 0.0
    rs = r[subset]
    return float(rs @ np.linalg.pinv(corr[np.ix_(subset, subset)], rcond=1e-12) @ rs)


def shapley_r2(corr: np.ndarray, r: np.ndarray, permutations: int = 2000,
               seed: int = 0) -> np.ndarray:
    """Shapley shares of the linear R^2 of y on d parameters (the LMG decomposition; Owen's
    Shapley effects of a linear model): each parameter's mean gain in R^2 when it joins a
    subset of the others, over all orders. They are >= 0 and sum to the full R^2, and
    parameters drawn correlated share what they explain together, so a parameter that
    explains nothing by itself gets little however its regression coefficient is inflated.
    Exact up to ``SHAPLEY_EXACT_MAX`` parameters, else over ``permutations`` random orders.
    ``corr``: (d, d) correlation matrix of the parameters; ``r``: (d,) their correlations
    with y."""
    d = r.shape[0]
    phi = np.zeros(d)
    if d <= SHAPLEY_EXACT_MAX:
        masks = (np.arange(2**d)[:, None] >> np.arange(d)) & 1
        val = np.array([_r2(corr, r, m.astype(bool)) for m in masks])
        size = masks.sum(axis=1)
        weight = np.array([math.factorial(k) * math.factorial(d - k - 1) / math.factorial(d)
                           for k in range(d)])
        for j in range(d):
            without = np.nonzero(masks[:, j] == 0)[0]
            phi[j] = np.sum(weight[size[without]] * (val[without + 2**j] - val[without]))
        return phi
    rng = np.random.default_rng(seed)
    perms = np.array([rng.permutation(d) for _ in range(permutations)])
    # the R^2 gains along an order are the squared last-row entries of the Cholesky factor of
    # the joint correlation matrix [[corr, r], [r, 1]] in that order (y last), all orders at once
    joint = np.block([[corr, r[:, None]], [r[None, :], np.ones((1, 1))]])
    order = np.concatenate([perms, np.full((permutations, 1), d)], axis=1)
    try:
        L = np.linalg.cholesky(joint[order[:, :, None], order[:, None, :]]
                               + 1e-10 * np.eye(d + 1))
        gains = L[:, d, :d] ** 2
    except np.linalg.LinAlgError:  # not positive definite to rounding: one R^2 at a time
        gains = np.empty((permutations, d))
        for p, perm in enumerate(perms):
            cur, prev = np.zeros(d, bool), 0.0
            for k, j in enumerate(perm):
                cur[j] = True
                v = _r2(corr, r, cur)
                gains[p, k], prev = v - prev, v
    np.add.at(phi, perms, gains)
    return phi / permutations


def sensitivities(cov: np.ndarray, cxy: np.ndarray, var_y: float,
                  labels: list[str]) -> list[dict[str, Any]]:
    """Sensitivities of a metric y to sampled parameters, valid when the draws are correlated.

    Per parameter: ``shapley`` (its share of the linear R^2, ``shapley_r2``: the ranking),
    ``corr`` (Pearson correlation with y: what it explains alone, its correlated partners'
    effects included), ``src`` (standardised regression coefficient: its effect with the
    others held fixed), ``vif`` (variance inflation factor of ``src``), ``r2_linear`` (R^2 of
    the full linear fit) and, where ``vif`` exceeds ``VIF_LIMIT``, ``collinear_with``: the
    parameters it is drawn correlated with (|corr| >= 0.9, else the others above the limit),
    whose separate effects these draws cannot tell apart. A parameter that does not vary gets
    zeros.

    **Arguments:**

    - ``cov``: (d, d) sample covariance of the parameters.
    - ``cxy``: (d,) their sample covariances with y.
    - ``var_y``: the sample variance of y.
    - ``labels``: the d parameter names.

    **Returns:**

    One dict per parameter, sorted by ``shapley``, largest first.
    """
    d = len(labels)
    sd_x = np.sqrt(np.clip(np.diag(cov), 0, None))
    live = sd_x > 0
    sd_y = math.sqrt(max(var_y, 0.0))
    corr_x = np.eye(d)
    r = np.zeros(d)
    if live.any():
        s = sd_x[live]
        corr_x[np.ix_(live, live)] = np.clip(cov[np.ix_(live, live)] / np.outer(s, s), -1, 1)
        if sd_y > 0:
            r[live] = np.clip(cxy[live] / (s * sd_y), -1, 1)
    src, vif = np.zeros(d), np.ones(d)
    phi = np.zeros(d)
    r2 = float("nan")
    if live.any() and sd_y > 0:
        sub = corr_x[np.ix_(live, live)]
        inv = np.linalg.pinv(sub, rcond=1e-12)
        src[live] = inv @ r[live]
        vif[live] = np.diag(inv)
        r2 = float(r[live] @ src[live])
        phi[live] = shapley_r2(sub, r[live])
    rows = []
    for j in range(d):
        row = {"parameter": labels[j], "shapley": float(phi[j]), "corr": float(r[j]),
               "src": float(src[j]), "vif": float(vif[j]), "r2_linear": r2}
        if live[j] and vif[j] > VIF_LIMIT:
            partners = [k for k in range(d) if k != j and live[k] and abs(corr_x[j, k]) >= 0.9]
            if not partners:
                partners = [k for k in range(d) if k != j and live[k] and vif[k] > VIF_LIMIT]
            row["collinear_with"] = [labels[k] for k in partners]
        rows.append(row)
    return sorted(rows, key=lambda row: -row["shapley"])


def collinear_warning(group: list[str]) -> str:
    """The warning for a group of parameters ``collinear_groups`` found."""
    return (f"{', '.join(group)} are drawn so correlated that their separate effects cannot "
            "be told apart; their Shapley shares split what they explain together, and their "
            "regression coefficients (src) are not meaningful")


def collinear_groups(rows: list[dict[str, Any]]) -> list[list[str]]:
    """The groups of parameters ``sensitivities`` marks as too collinear to separate (each
    sorted, each once)."""
    groups: list[list[str]] = []
    for row in rows:
        if "collinear_with" in row:
            g = sorted({row["parameter"], *row["collinear_with"]})
            if g not in groups:
                groups.append(g)
    return groups


def _gather_samples(kept: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """All processes' kept samples (padded to the largest share, then unpadded)."""
    from jax.experimental import multihost_utils as mu

    mine = {k: np.concatenate([c[k] for c in kept]) for k in kept[0]} if kept else None
    if mine is None:
        raise ValueError("allgather of kept samples: a process ran no chunk (use fewer processes)")
    n = np.array([mine["index"].size])
    sizes = np.asarray(mu.process_allgather(n)).reshape(-1)
    m = int(sizes.max())
    out = {}
    for k, v in mine.items():
        pad = np.zeros((m - v.shape[0],) + v.shape[1:], float)
        g = np.asarray(mu.process_allgather(np.concatenate([v.astype(float), pad])))
        out[k] = np.concatenate([g[p, : sizes[p]] for p in range(len(sizes))])
    out["index"] = out["index"].astype(np.int64)
    out["diverged"] = out["diverged"].astype(bool)
    return out
