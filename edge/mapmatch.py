"""Map matching: GNSS fixes to the routes of a network, by a hidden Markov model solved with Viterbi.

At each fix the hidden state is one candidate: a route within ``radius_m`` of the fix (its nearest
point: chainage and offset) or *off the network*. Emissions are Gaussian in the offset with the
fix's own 1σ (``gnss_accuracy_m``, floored). Transitions follow Newson & Krumm (2009): between two
fixes the network distance (along one route, or through a junction into another) should equal the
straight-line distance between the fixes; the difference is exponentially distributed with scale
``beta_m``, and changing route away from a junction is impossible. Off-network is a state with a
flat emission (a fix farther than ``radius_m`` from every route) and a switching cost, so a drive
on unmapped roads is not forced onto the network. Forward–backward posteriors mark *ambiguous*
fixes: where the chosen route's posterior probability falls below ``min_posterior``, or another
route passes within ``margin_sigmas`` of the fix's own error (parallel roads, junctions), a fix is
not trusted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from pyproj import Geod

from shared.geo import RouteGeometry

_WGS84 = Geod(ellps="WGS84")
OFF = -1  # the route index of the off-network state


@dataclass(frozen=True)
class MatchSettings:
    """``radius_m``: candidates within this distance of a fix; ``sigma_floor_m``: the smallest 1σ
    trusted for a fix; ``default_sigma_m``: 1σ of fixes without an accuracy; ``beta_m``: scale of
    the network-vs-straight distance mismatch per transition; ``junction_m``: two routes meet where
    their lines come this close; ``off_network_cost``: −log probability of entering or leaving the
    off-network state; ``min_posterior``: the matched route's posterior below which a fix is
    ambiguous; ``margin_sigmas``: a fix is also ambiguous when another route passes within this
    many of its 1σ of the chosen route's offset."""

    radius_m: float = 30.0
    sigma_floor_m: float = 1.0
    default_sigma_m: float = 5.0
    beta_m: float = 5.0
    junction_m: float = 3.0
    off_network_cost: float = 10.0
    min_posterior: float = 0.95
    margin_sigmas: float = 2.0

    def __post_init__(self):
        for k, v in self.__dict__.items():
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"MatchSettings.{k}: must be a positive finite number, got {v!r}")
        if self.min_posterior >= 1.0:
            raise ValueError(f"MatchSettings.min_posterior: must be below 1, got {self.min_posterior!r}")


class Junction(NamedTuple):
    a: int  # route index
    chainage_a: float
    b: int
    chainage_b: float


class Network(NamedTuple):
    """The routes a drive is matched to, and where they meet."""

    route_ids: tuple[str, ...]
    geometries: tuple[RouteGeometry, ...]
    junctions: tuple[Junction, ...]


class Match(NamedTuple):
    """Per fix: the matched route index (``OFF`` off the network), chainage (m), offset (m) and
    the posterior probability of that route; ``ambiguous`` where it is below the settings'."""

    route: np.ndarray  # (k,) int
    chainage: np.ndarray  # (k,) m (NaN off the network)
    offset: np.ndarray  # (k,) m
    posterior: np.ndarray  # (k,)
    ambiguous: np.ndarray  # (k,) bool


def build_network(routes: dict[str, RouteGeometry], settings: MatchSettings = MatchSettings(),
                  step_m: float = 2.0) -> Network:
    """The network of ``routes`` (id → geometry) with its junctions: each place (one per
    ``junction_m`` neighbourhood) where two routes' lines come within ``junction_m``."""
    ids = tuple(sorted(routes))
    geoms = tuple(routes[i] for i in ids)
    found: list[Junction] = []
    for a, ga in enumerate(geoms):
        s = np.append(np.arange(0.0, ga.length_m, step_m), ga.length_m)
        lat, lon = ga.position(s)
        for b, gb in enumerate(geoms):
            if b <= a:
                continue
            cb, off = gb.locate(lat, lon)
            close = off < settings.junction_m
            # One junction per contiguous run of close samples: the closest sample of the run.
            edges = np.flatnonzero(np.diff(np.concatenate(([0], close.astype(int), [0]))))
            for i0, i1 in zip(edges[::2], edges[1::2]):
                k = i0 + int(np.argmin(off[i0:i1]))
                found.append(Junction(a, float(s[k]), b, float(cb[k])))
    return Network(ids, geoms, tuple(found))


def _distance(lat1, lon1, lat2, lon2) -> np.ndarray:
    _, _, d = _WGS84.inv(lon1, lat1, lon2, lat2)
    return np.asarray(d, float)


def _network_distance(net: Network, ra: int, ca: float, rb: int, cb: np.ndarray) -> np.ndarray:
    """Shortest distance along the network from (route ``ra``, chainage ``ca``) to each (``rb``,
    ``cb``) through at most one junction (fixes are seconds apart)."""
    best = np.full(np.shape(cb), np.inf)
    if ra == rb:
        best = np.abs(cb - ca)
    for j in net.junctions:
        if {j.a, j.b} == {ra, rb} and ra != rb:
            ja, jb = (j.chainage_a, j.chainage_b) if j.a == ra else (j.chainage_b, j.chainage_a)
            best = np.minimum(best, abs(ca - ja) + np.abs(cb - jb))
    return best


def match(net: Network, lat: np.ndarray, lon: np.ndarray, accuracy_m: np.ndarray | None = None,
          settings: MatchSettings = MatchSettings()) -> Match:
    """Match the fixes ``lat``/``lon`` (degrees, in time order) to ``net``.

    ``accuracy_m`` is each fix's 1σ (m; NaN or None → ``default_sigma_m``).
    """
    lat = np.asarray(lat, float)
    lon = np.asarray(lon, float)
    k = len(lat)
    R = len(net.geometries)
    sigma = np.full(k, settings.default_sigma_m)
    if accuracy_m is not None:
        acc = np.asarray(accuracy_m, float)
        sigma = np.where(np.isfinite(acc), acc, sigma)
    sigma = np.maximum(sigma, settings.sigma_floor_m)
    ch = np.empty((k, R))
    off = np.empty((k, R))
    for r, g in enumerate(net.geometries):
        ch[:, r], off[:, r] = g.locate(lat, lon)
        # A fix beyond a route's end maps to the end with a true offset: no special case needed.
    # States 0..R-1: routes; state R: off the network.
    emit = np.full((k, R + 1), -np.inf)
    near = off <= settings.radius_m
    emit[:, :R] = np.where(near, -0.5 * (off / sigma[:, None]) ** 2 - np.log(sigma[:, None]), -np.inf)
    emit[:, R] = -0.5 * (settings.radius_m / sigma) ** 2 - np.log(sigma)
    straight = np.zeros(k)
    if k > 1:
        straight[1:] = _distance(lat[:-1], lon[:-1], lat[1:], lon[1:])

    def trans(i: int) -> np.ndarray:
        """log P(state at fix i | state at fix i − 1), (R + 1, R + 1)."""
        T = np.full((R + 1, R + 1), -np.inf)
        for a in range(R):
            if not near[i - 1, a]:
                continue
            d = np.array([_network_distance(net, a, ch[i - 1, a], b, ch[i, b]) for b in range(R)], float)
            T[a, :R] = -np.abs(d - straight[i]) / settings.beta_m - math.log(settings.beta_m)
        T[:R, R] = -settings.off_network_cost
        T[R, :R] = -settings.off_network_cost
        T[R, R] = 0.0
        return T

    Ts = [None] + [trans(i) for i in range(1, k)]
    # Viterbi.
    score = emit[0].copy()
    back = np.zeros((k, R + 1), int)
    for i in range(1, k):
        cand = score[:, None] + Ts[i]
        back[i] = np.argmax(cand, axis=0)
        score = cand[back[i], np.arange(R + 1)] + emit[i]
    path = np.empty(k, int)
    path[-1] = int(np.argmax(score))
    for i in range(k - 1, 0, -1):
        path[i - 1] = back[i, path[i]]
    # Forward–backward (log domain) for the posterior of each state.
    fwd = np.empty((k, R + 1))
    fwd[0] = emit[0] - _lse(emit[0])
    for i in range(1, k):
        f = _lse_cols(fwd[i - 1][:, None] + Ts[i]) + emit[i]
        fwd[i] = f - _lse(f)
    bwd = np.zeros((k, R + 1))
    for i in range(k - 1, 0, -1):
        b = _lse_rows(Ts[i] + (emit[i] + bwd[i])[None, :])
        bwd[i - 1] = b - _lse(b)
    post = fwd + bwd
    post = np.exp(post - _lse_rows(post)[:, None])
    route = np.where(path == R, OFF, path)
    idx = np.arange(k)
    chain = np.where(route >= 0, ch[idx, np.clip(path, 0, R - 1)], np.nan)
    offset = np.where(route >= 0, off[idx, np.clip(path, 0, R - 1)], np.min(off, axis=1))
    p = post[idx, path]
    # The posterior pools evidence over the whole drive as if fix errors were independent; they are
    # not (GNSS error wanders over tens of seconds), so a fix must also tell the routes apart itself:
    # another route within margin_sigmas of its own 1σ of the chosen one's offset makes it ambiguous.
    others = np.where(np.arange(R)[None, :] == np.clip(path, 0, R - 1)[:, None], np.inf, off)
    margin = np.min(others, axis=1) - offset if R > 1 else np.full(k, np.inf)
    ambiguous = (p < settings.min_posterior) | ((route >= 0) & (margin < settings.margin_sigmas * sigma))
    return Match(route, chain, offset, p, ambiguous)


def _lse(x: np.ndarray) -> float:
    m = np.max(x)
    return float(m + np.log(np.sum(np.exp(x - m)))) if np.isfinite(m) else -np.inf


def _lse_cols(X: np.ndarray) -> np.ndarray:
    m = np.max(X, axis=0)
    safe = np.where(np.isfinite(m), m, 0.0)
    return np.where(np.isfinite(m), safe + np.log(np.sum(np.exp(X - safe[None, :]), axis=0)), -np.inf)


def _lse_rows(X: np.ndarray) -> np.ndarray:
    return _lse_cols(X.T)
