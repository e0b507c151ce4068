"""One bridge's live posterior: passes in, stiffness / weights / MR-IL / damage assessment out.

Transport-free: :meth:`BridgeEstimator.add_segments` takes one pass's AP segments (with the vehicle
parameters the edge used), :meth:`BridgeEstimator.estimate` returns the current
:class:`BridgeEstimate`. What can be cached per pass is (the pass's corrected AP, its band-limited
model columns, its dynamic correction while the stiffness estimate stays put, its wheel-load factor
from the consensus road — recomputed with its load columns when the fleet has grown by a quarter);
what depends on the whole fleet (the consensus, hence each pass's residual and noise level) is
recomputed at every estimate, at O(passes) small cost. The dynamic excess of every pass is cached
per global level (on :data:`~cloud.bridge.dynamic.LEVEL_GRID`), so an update recomputes it for the
new pass and for levels not visited before; its derivatives in each element's stiffness at the
linearisation level, which is kept while the level stays within
:data:`~cloud.bridge.dynamic.LINEARISATION_TOL` of it (so an update computes them for the new pass only).

The MR-IL and the indicators D1/D2 come from the posterior influence line (the fleet's deflection
per unit static wheel load with the dynamics modelled out); the thesis's per-pass reading is kept
as :attr:`BridgeEstimate.mril_passes`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from shared.registry import Bridge, Site
from shared.schema import ApSegment
from shared.vehicles import GRAVITY, vehicle_from_params
from shared.vehicles.calibration import calibration_names

from cloud.bridge.basis import mu_basis, step_basis
from cloud.bridge.dynamic import GlobalLevel, fit_elements_dynamic
from cloud.bridge.hypotheses import Assessment, HypothesisSettings, Kernels, assess
from cloud.bridge.likelihood import Stacked, WeightPrior, marginal_loglik_batch, vehicle_stats
from cloud.bridge.mril import Baseline, DamageIndicators, MrIl, damage_indicators, mril_single_axle
from cloud.bridge.passdata import EdgeSettings, PassData, Reference, extract_pass, road_load_factor, span_profile
from cloud.bridge.posterior import ElementPosterior, fit_elements
from cloud.bridge.registration import MIN_SHIFT_M, register, shift_pass
from cloud.bridge.setup import Setup
from cloud.bridge.stiffness import StiffnessPrior
from cloud.bridge.vehicle_error import class_log_sd
from cloud.bridge.whitening import (Whitener, common_calibration_columns, consensus_distortion, driven_road,
                                    model_columns, pass_distortion, road_sensitivity, whiten_pass)

LOAD_FACTORS = ("road", "own")
#: A pass's wheel-load factor from the consensus road is recomputed when the passes behind the
#: consensus have grown by this factor since (its error from the consensus' noise falls as 1/√n).
LOAD_FACTOR_REFRESH = 1.25


@dataclasses.dataclass(frozen=True)
class BridgeSettings:
    """How a bridge is estimated.

    ``deck``: "smooth" (deck profile known flat) or "rough" (an unknown common deck profile);
    ``dynamic``: moving-force dynamics on (:func:`~cloud.bridge.dynamic.fit_elements_dynamic`,
    warm-started at the last level; each pass's correction is cached per level);
    ``baseline_passes``: learn the MR-IL baseline from the first passes (None: the design MR-IL).
    ``assess``: run the damage hypotheses and the alarm; ``assess_rough``: on a rough deck too (a
    registry's bridge is rough unless it declares otherwise, so off would leave most bridges without
    an alarm). On a rough deck the common deck profile takes most of what a smooth deck's passes
    say about the stiffness along the span: the hypotheses still tell a healthy span from a damaged
    one, but locate a crack only to a few metres and need a deeper one for the same passes.
    """

    deck: str = "smooth"
    edge: EdgeSettings = EdgeSettings()
    stiffness_prior: StiffnessPrior = StiffnessPrior()
    hypotheses: HypothesisSettings = HypothesisSettings()
    dynamic: bool = True
    #: the per-element fit linearises each pass's dynamic excess in every element's stiffness
    #: (:func:`~cloud.bridge.dynamic.fit_elements_dynamic`); False: the excess at the profile-likelihood
    #: level only, the fit recentred on it (see the module docstring of :mod:`cloud.bridge.dynamic`
    #: for what each costs)
    dynamic_sensitivities: bool = True
    min_passes: int = 3
    baseline_passes: int | None = None
    assess: bool = True
    assess_rough: bool = True
    #: log-sd of every calibration quantity of a pass added without its own
    #: (:meth:`BridgeEstimator.add_segments`): the calibration error integrated out of the likelihood
    #: (:mod:`cloud.bridge.vehicle_error`). The default is the error fleet self-calibration leaves
    #: (30 quarter-cars at 2 % noise leave rms log errors of 0.5–3.7 % per quantity, c/M the
    #: worst); None: parameters taken as exact.
    calibration_log_sd: float | None = 0.04
    #: prior of the calibration error every pass of the vehicle class shares (the fleet-common mode
    #: that fleet agreement cannot see, :mod:`cloud.bridge.vehicle_error`), integrated out jointly
    #: across passes: "mean" — log-sd σ_class/√N per quantity, the error of the class prior's mean as
    #: the mean of N vehicles drawn from the class (N: vehicles with calibrated passes on the bridge,
    #: at most the number calibrated, so this errs wide); "class" — σ_class (the fleet may differ
    #: from the class as a whole); None — not modelled.
    common_calibration: str | None = "mean"
    #: where each pass's dynamic wheel-load factor ``1 + φ_p`` comes from: "road" — the vehicle's
    #: forward model over the fleet's leave-one-out consensus road and its own deflection under the
    #: class-mean load (:func:`~cloud.bridge.passdata.road_load_factor`), recomputed as the fleet grows
    #: (:data:`LOAD_FACTOR_REFRESH`); "own" — over the pass's own AP (:func:`~cloud.bridge.passdata.extract_pass`),
    #: which carries the pass's noise into the regressor the same noise is fitted with (errors in
    #: variables; see :meth:`BridgeEstimator._load_factor`).
    load_factor: str = "road"
    #: register every pass to the others along the window from the road off the span before each
    #: estimate (:mod:`cloud.bridge.registration`): the estimators need the passes placed to a few
    #: millimetres, which a per-run odometer error, GNSS or a logger's filter delay do not give
    register: bool = True


def class_weight_prior(site: Site, model: str) -> WeightPrior:
    """Static wheel load prior of a single-contact vehicle class: mean and sd of (M + m)·g (N),
    with the class's spread of each calibration quantity (log-sd, the scale of the fleet-common
    calibration error, :attr:`BridgeSettings.common_calibration`).

    Absolute masses are not identifiable from road data: the class mean is the scale
    (thesis §4.5.5); a vehicle's ratio m/M does not change the prior mean to first order.
    """
    vc = site.vehicle_class(model)
    mean = vehicle_from_params(model, dict(vc.mean)).system().static_contact_forces()
    if mean.size != 1:
        raise ValueError("class_weight_prior: single-contact vehicle classes only")
    mass_names = [k for k in vc.mean if k in ("M", "m")] or list(vc.mean)[:1]
    sd = math.sqrt(sum(vc.std.get(k, 0.0) ** 2 for k in mass_names)) * GRAVITY
    try:
        spread = tuple(sorted(class_log_sd(site, model).items()))
    except (KeyError, ValueError):
        spread = ()
    return WeightPrior(float(mean[0]), float(sd), class_log_sd=spread)


@dataclasses.dataclass(frozen=True, eq=False)
class PassDeflections:
    """Each pass's drift-controlled deflection under its wheel as the estimate read it: on the span
    points ``x_m`` (m from the first support), down positive (m), with the bridge's own dynamics (the
    moving-force excess at the posterior's wheel load) taken out; ``loads_n`` the pass's posterior
    static wheel load (N); ``keys`` (vehicle, pass). What the per-pass MR-IL averages
    (:attr:`BridgeEstimate.mril_passes`: deflection over load), and what a reference method given
    "the passes' deflections" should be given."""

    x_m: np.ndarray
    keys: tuple[tuple[str, str], ...]
    deflection_m: tuple[np.ndarray, ...]
    loads_n: tuple[float, ...]


@dataclasses.dataclass(frozen=True, eq=False)
class BridgeEstimate:
    """Everything the cloud reports about one bridge (interfaces.md §3 rows via the methods)."""

    bridge: Bridge
    posterior: ElementPosterior
    quasi_static: ElementPosterior
    assessment: Assessment | None
    mril: MrIl
    indicators: DamageIndicators | None
    n_passes: int
    level: GlobalLevel | None = None  # the dynamic model's profile-likelihood global level
    mril_passes: MrIl | None = None  # the thesis's per-pass MR-IL (quasi-static reading), for comparison
    pass_deflections: PassDeflections | None = None  # what ``mril_passes`` was read from

    def element_rows(self) -> list[dict]:
        return self.posterior.rows(self.bridge.id)

    def bearing_rows(self) -> list[dict]:
        if self.posterior.krot is None:
            return []
        return [dict(bridge_id=self.bridge.id, support=i + 1, log10_krot_mean=k[0], log10_krot_lo95=k[1],
                     log10_krot_hi95=k[2]) for i, k in enumerate(self.posterior.krot)]

    def summary_row(self) -> dict:
        ind = self.indicators
        return dict(bridge_id=self.bridge.id, n_passes=self.n_passes,
                    D1_pct=float("nan") if ind is None else ind.D1_pct,
                    D2_pct=float("nan") if ind is None else ind.D2_pct,
                    midspan_mril=self.mril.midspan(),
                    damaged=bool(self.assessment.alarm) if self.assessment is not None else False)


@dataclasses.dataclass
class _PassEntry:
    data: PassData
    columns: tuple[Whitener, np.ndarray, tuple | None] | None  # None: not yet computed (model_columns)
    load_at: int | None = None  # passes in the consensus its road load factor was computed with
    road: tuple[int, np.ndarray] | None = None  # (passes in the consensus, its road sensitivity)
    common: np.ndarray | None = None  # its fleet-common calibration columns, band-limited forward model
    raw: PassData | None = None  # the pass as extracted, before registration moved it (``data``)
    shift_m: float = 0.0  # how far registration moved it


class BridgeEstimator:
    """Live estimation for one bridge (single-contact vehicles: axle 1 of each pass)."""

    def __init__(self, bridge: Bridge, weight_prior: WeightPrior, settings: BridgeSettings = BridgeSettings()):
        self.bridge = bridge
        self.weight_prior = weight_prior
        self.settings = settings
        if settings.load_factor not in LOAD_FACTORS:
            raise ValueError(f"load_factor: must be one of {LOAD_FACTORS}, got {settings.load_factor!r}")
        self.setup = Setup.of(bridge, deck=settings.deck)
        self.model = self.setup.model(settings.stiffness_prior)
        use = settings.assess and (settings.deck == "smooth" or settings.assess_rough)
        self.kernels = Kernels.of(self.setup) if use else None
        self.passes: dict[tuple[str, str], _PassEntry] = {}
        self.baseline = (Baseline.declared(bridge, self.setup.basis.x) if settings.baseline_passes is None
                         else Baseline.learnt(settings.baseline_passes))
        self._scale = 1.0  # uniform stiffness ratio of the dynamic correction
        self._linearise_at: np.ndarray | None = None  # bearing models: the last estimate's parameters
        self._cache: dict = {}  # (vehicle, pass, parameters[, "dtheta"]) → dynamic excess on the window (or ∂ε/∂θ)
        self._linearised_level: float | None = None  # where the last fit linearised the dynamics (log ratio)
        self._common_at: tuple | None = None  # (passes, names, consensus distortion) of the common columns

    # -- data ------------------------------------------------------------------------------
    def add_segments(self, segments: Sequence[ApSegment], model: str, params: dict,
                     params_log_sd: dict | None = None, sample_interval_s: float | None = None) -> bool:
        """Add one pass from its segments (all tiles, all axles); False if it does not cross the bridge.

        ``sample_interval_s``: the step the edge inverted the pass at (its pass-done says; the edge
        inverse's discretisation, which the pass's model undoes, depends on it); default
        ``settings.edge``'s.

        ``params_log_sd``: the calibration's uncertainty, log-sd per calibration quantity
        (:func:`~cloud.bridge.vehicle_error.fit_log_sd` of a calibrator's fit, or
        :func:`~cloud.bridge.vehicle_error.class_log_sd` for a vehicle at its class mean); default
        ``settings.calibration_log_sd`` on every quantity.
        """
        if params_log_sd is None and self.settings.calibration_log_sd:
            params_log_sd = {n: self.settings.calibration_log_sd for n in calibration_names(model)}
        edge = self.settings.edge
        if sample_interval_s is not None and abs(sample_interval_s * edge.sample_rate_hz - 1.0) > 1e-9:
            edge = dataclasses.replace(edge, sample_rate_hz=1.0 / sample_interval_s)
        pd = extract_pass(segments, self.setup.window, model, params, edge=edge, params_log_sd=params_log_sd)
        if pd is None:
            return False
        self.add(pd)
        return True

    def add(self, pd: PassData) -> None:
        """Add (or replace, e.g. after recalibration) one pass. Its model columns are computed at the
        next estimate, once its wheel-load factor is known (:attr:`BridgeSettings.load_factor`)."""
        self.passes[(pd.vehicle_id, pd.pass_id)] = _PassEntry(pd, None, raw=pd)
        self._forget((pd.vehicle_id, pd.pass_id))

    def remove(self, vehicle_id: str, pass_id: str) -> None:
        self.passes.pop((vehicle_id, pass_id), None)

    @property
    def n_passes(self) -> int:
        return len(self.passes)

    # -- estimation --------------------------------------------------------------------------
    def estimate(self) -> BridgeEstimate | None:
        """The current estimate (None before ``min_passes`` passes)."""
        entries = list(self.passes.values())
        if len(entries) < self.settings.min_passes:
            return None
        if self.settings.register:
            self._register(entries)
        ref = Reference.of([e.data for e in entries])
        # The calibration error is linearised at the class-mean load and the design influence line, or
        # for bearings at the last estimate: the bearings' prior mean (Krot 1e8, nearly pinned) is far
        # from a stiff bearing's line, and linearising there reads a stiff bearing stiffer still.
        load = self.model.a(self._linearise_at if self._linearise_at is not None else self.model.prior_mean())
        for e in entries:
            self._load_factor(e, ref, load)
        common = self._common(entries)
        cols = self._common_columns(entries, ref, common, load)
        wps = [whiten_pass(e.data, ref, self.setup.basis, self.settings.deck, columns=e.columns, load=load,
                           weight_n=self.weight_prior.mean_n, road=self._road(e, ref), common=common,
                           common_columns=c) for e, c in zip(entries, cols)]
        level_loglik = level = None
        if self.settings.dynamic:
            fit = fit_elements_dynamic(wps, self.setup, self.weight_prior, model=self.model, start=self._scale,
                                       cache=self._cache, linearise_at=self._linearised_level,
                                       sensitivities=self.settings.dynamic_sensitivities)
            qs, post, deltas, self._scale, level = fit.history[0], fit.posterior, fit.deltas, fit.scale, fit.level
            if post.krot is not None:
                self._linearise_at = np.r_[post.theta, [k[0] for k in post.krot]][: self.model.n]
            else:
                self._linearised_level = float(fit.linearisation[0])
            self._prune_cache(fit.linearisation, () if level is None else tuple(level.evaluations))
            if level is not None and self.kernels is not None:
                level_loglik = self._level_loglik(wps, deltas, level)
        else:
            qs = post = fit_elements(vehicle_stats(wps), self.model, self.weight_prior)
            deltas = None
        assessment = None
        if self.kernels is not None:
            assessment = assess(vehicle_stats(wps, deltas), self.setup, self.weight_prior,
                                self.settings.hypotheses, kernels=self.kernels, level_loglik=level_loglik)
        # The MR-IL the indicators read is the posterior's influence line (the fleet's deflection
        # per unit wheel load, the bridge's vibration and the vehicles' dynamic loads modelled out).
        # The thesis's reading — each pass's deflection over its load, averaged — is kept as
        # ``mril_passes``: at 2 % noise its per-pass drift control leaves errors of tens of per cent
        # in its area.
        mril = MrIl(self.setup.basis.x, self.model.influence(post.params), len(entries))
        pass_deflections = self._pass_deflections(entries, wps, ref, post, deltas)
        mril_passes = mril_single_axle(pass_deflections.x_m, pass_deflections.deflection_m, pass_deflections.loads_n)
        if post.krot is not None and self.settings.baseline_passes is None:
            self.baseline = self._declared_on_bearings(post)
        self.baseline.offer(mril)
        indicators = damage_indicators(self.baseline.mril, mril) if self.baseline.ready else None
        return BridgeEstimate(self.bridge, post, qs, assessment, mril, indicators, len(entries), level, mril_passes,
                              pass_deflections)

    def _forget(self, key: tuple[str, str]) -> None:
        """Drop what the cache holds for the pass ``key`` (vehicle, pass): its data changed."""
        self._cache = {k: v for k, v in self._cache.items() if (k[0], k[1]) != key}

    def _register(self, entries: list[_PassEntry]) -> None:
        """Move every pass to where its road agrees with the others' (:mod:`cloud.bridge.registration`).
        A pass moved again only when its shift has changed by more than the registration resolves
        keeps its cached columns otherwise (each move recomputes them, and the fleet's common columns)."""
        shifts = register([e.raw for e in entries])
        moved = False
        for e, s in zip(entries, shifts):
            if abs(s - e.shift_m) < MIN_SHIFT_M:
                continue
            e.data, e.shift_m = shift_pass(e.raw, s), s
            e.columns = e.load_at = e.road = e.common = None
            self._forget((e.data.vehicle_id, e.data.pass_id))
            moved = True
        if moved:
            self._common_at = None

    def _declared_on_bearings(self, post: ElementPosterior) -> Baseline:
        """The declared baseline of a span on rotational springs: the design E·I on the bearings the
        posterior reads. D1/D2 read a loss of flexural rigidity; against the pinned design span the
        bearings' restraint alone reads as a stiffness gain of the order of the restraint (a stiff
        bearing halves the mid-span ordinate), which says nothing about the beam. The bearings are
        read from the passes with the beam (and so are not a second opinion on it), but what the
        passes fix is the span's effective stiffness, and its split between beam and bearings is the
        posterior's: D then reads the beam's share, as the elements do — on the bearings the posterior's
        influence line stands on (its parameters' κ, the mode the fit is conditioned on, not the
        reported mean of log10 Krot)."""
        krot = 10.0 ** np.clip(np.asarray(post.params, dtype=float)[self.model.n_elements :], -3.0, 16.0)
        return Baseline.declared(self.bridge, self.setup.basis.x, (float(krot[0]), float(krot[-1])))

    def _load_factor(self, e: _PassEntry, ref: Reference, load: np.ndarray) -> None:
        """Give the pass its wheel-load factor (:attr:`BridgeSettings.load_factor`) and its model columns.

        "road": ``1 + φ_p`` of the vehicle driven over the leave-one-out consensus road
        (:func:`~cloud.bridge.whitening.driven_road`) and, on a smooth deck's span (where that road is
        taken flat), its own deflection under the class-mean wheel load ``W̄·J`` at the linearisation
        load term ``load`` (a rough deck's consensus holds the fleet-mean deflection already). It
        holds none of the pass's own noise. A φ̂ read from the pass's own AP errs mostly at 2–10 Hz,
        where its error is the pass's AP noise — the noise the pass is then fitted against, which reads
        the bridge soft. The road's φ errs a little more in total (less in that band, more below 2 Hz,
        where the vehicle's own weight and the bridge's vibration are not in it), but none of its error is
        correlated with the pass's noise.

        Recomputed when the passes behind the consensus have grown by :data:`LOAD_FACTOR_REFRESH`
        (then only the load columns of :func:`~cloud.bridge.whitening.model_columns` are redone: the μ
        and step columns do not depend on φ, and the calibration sensitivities of the load columns
        and the cached dynamic excess move by ~Δφ ≈ 10⁻⁴ of themselves, far below their own
        uncertainty, so they are kept). Passed in live one by one, the final estimate is the batch one's
        to a small fraction of a point per element, and the refreshes are a small part of the estimates'
        cost.
        """
        if self.settings.load_factor == "road":
            n = int(ref.count.max())
            if e.load_at is None or n > LOAD_FACTOR_REFRESH * e.load_at:
                window, deck = self.setup.window, self.settings.deck
                road = driven_road(e.data, ref, deck)
                deflection = None
                if deck == "smooth":
                    deflection = np.zeros(window.n)
                    deflection[window.on_span] = self.weight_prior.mean_n * (self.setup.basis.design @ load)
                e.data = dataclasses.replace(e.data, load_factor=road_load_factor(e.data, road, deflection))
                e.load_at = n
                if e.columns is not None:
                    skeleton, white, sens = e.columns
                    skeleton = dataclasses.replace(skeleton, data=e.data)
                    basis, on = self.setup.basis, window.on_span
                    cols = np.zeros((window.n, basis.n))
                    cols[on] = e.data.load_factor[on, None] * basis.design
                    white = white.copy()
                    white[:, : basis.n] = skeleton.stage1(cols)
                    e.columns = (skeleton, white, sens)
        if e.columns is None:
            e.columns = model_columns(e.data, self.setup.basis, self.settings.deck)

    def _common(self, entries: list[_PassEntry]) -> tuple[tuple[str, float], ...] | None:
        """(name, prior log-sd) of the fleet-common calibration error's coordinates, or None."""
        how = self.settings.common_calibration
        spread = self.weight_prior.class_log_sd
        if how is None or not spread:
            return None
        if how not in ("mean", "class"):
            raise ValueError(f"common_calibration: 'mean', 'class' or None, got {how!r}")
        n = len({e.data.vehicle_id for e in entries if e.data.params_log_sd})
        if n == 0:
            return None
        k = 1.0 / math.sqrt(n) if how == "mean" else 1.0
        return tuple((name, s * k) for name, s in spread if s > 0)

    def _common_columns(self, entries: list[_PassEntry], ref: Reference, common, load: np.ndarray) -> list:
        """Every pass's band-limited forward model of its fleet-common calibration columns
        (:func:`~cloud.bridge.whitening.common_calibration_columns`). They are a nuisance's shape, not
        data: all are recomputed when the fleet has grown by a quarter since (the consensus and its
        distortion move), a new pass's against the consensus distortion of then — so an update
        costs one pass's columns, amortised."""
        if not common:
            return [None] * len(entries)
        names = tuple(n for n, _ in common)
        window, on, deck = self.setup.window, self.setup.window.on_span, self.settings.deck
        J = self.setup.basis.design @ load

        def deflection(e: _PassEntry) -> np.ndarray:
            d = np.zeros(window.n)
            d[on] = -self.weight_prior.mean_n * e.data.load_factor[on] * J
            return d

        at = self._common_at
        if at is None or len(entries) > 1.25 * at[0] or at[1] != names:
            cols, us = common_calibration_columns([e.data for e in entries], ref, names, deck,
                                                  [deflection(e) for e in entries])
            for e, c in zip(entries, cols):
                e.common = e.columns[0].stage1(c)
            self._common_at = (len(entries), names, consensus_distortion(us, window, deck))
        else:
            for e in entries:
                if e.common is None:
                    u = pass_distortion(e.data, ref, names, deck, deflection(e))
                    e.common = e.columns[0].stage1(u - at[2])
        return [e.common for e in entries]

    def _road(self, e: _PassEntry, ref: Reference) -> np.ndarray | None:
        """The pass's calibration sensitivity to the consensus road, recomputed when the fleet behind
        the consensus has grown by a quarter since (it is a nuisance's shape, not data)."""
        if e.columns[2] is None:
            return None
        n = int(ref.count.max())
        if e.road is None or n > 1.25 * e.road[0]:
            e.road = (n, road_sensitivity(e.data, ref, e.columns[0], e.columns[2][0], self.settings.deck))
        return e.road[1]

    def _level_loglik(self, wps, deltas, level: GlobalLevel):
        """What the dynamics say about the global level beyond the fixed-ε likelihood the hypotheses
        use: the profile log-likelihood minus the fixed-ε one, both quadratic in the level g."""
        S = Stacked.of(vehicle_stats(wps, deltas), self.weight_prior)
        sd = level.sd if np.isfinite(level.sd) else 0.02
        gs = level.log_ratio + sd * np.array([-2.0, -1.0, 0.0, 1.0, 2.0])
        lin = np.zeros((gs.size, self.model.n))
        lin[:, : self.model.n_elements] = gs[:, None]
        a = np.array([self.model.a(row) for row in lin])
        c2, c1, _ = np.polyfit(gs - level.log_ratio, marginal_loglik_batch(S, a), 2)
        i_fixed = max(-2.0 * c2, 0.0)
        g_fixed = level.log_ratio - c1 / (2 * c2) if c2 < 0 else level.log_ratio
        i_prof = 1.0 / sd**2
        i_extra_ok = i_prof > i_fixed

        def extra(g: np.ndarray) -> np.ndarray:
            prof = -0.5 * i_prof * (g - level.log_ratio) ** 2
            fixed = -0.5 * i_fixed * (g - g_fixed) ** 2
            return prof - fixed if i_extra_ok else np.zeros_like(g)

        return extra

    def _prune_cache(self, lin: np.ndarray, levels=()) -> None:
        """Keep the dynamic excesses of passes still present at the current linearisation and at
        the global levels the last search visited (the next update revisits most of them)."""
        keep = {tuple(np.round(np.asarray(lin, dtype=float), 9))}
        for g in levels:
            row = np.array(lin, dtype=float)
            row[: self.model.n_elements] = g
            keep.add(tuple(np.round(row, 9)))
        self._cache = {k: v for k, v in self._cache.items() if k[2] in keep and (k[0], k[1]) in self.passes}
        self._current = tuple(np.round(np.asarray(lin, dtype=float), 9))

    def _excess(self, e: "_PassEntry") -> np.ndarray | None:
        return self._cache.get((e.data.vehicle_id, e.data.pass_id, getattr(self, "_current", None)))

    def _pass_deflections(self, entries: list[_PassEntry], wps, ref: Reference, post: ElementPosterior,
                          dyn) -> PassDeflections:
        """Each pass's drift-controlled deflection and estimated wheel load (single-axle vehicles),
        less the bridge's own dynamics (the moving-force excess W·ε_p of the dynamic model, where
        the thesis low-passes the mean MR-IL instead): the fleet's fundamental MR-IL is their ratio,
        averaged (:func:`~cloud.bridge.mril.mril_single_axle`)."""
        deltas, loads = [], []
        x = None
        window, deck = self.setup.window, self.settings.deck
        mb = mu_basis(window, self.setup.basis, deck)
        common = mb @ post.mu[: mb.shape[1]]  # the deck's μ (the calibration coordinates follow)
        steps = step_basis(window, deck)
        a = self.model.a(post.params)
        for e, wp in zip(entries, wps):
            weight = post.weights.get(e.data.vehicle_id, (self.weight_prior.mean_n, 0.0))[0]
            excess = None if dyn is None else self._excess(e)
            delta = None if excess is None else wp.whitener.raw(excess)
            own = steps @ wp.step_coefficients(a, weight, post.mu, delta) if steps.shape[1] else 0.0
            sp = span_profile(e.data, ref, common=common + own, smooth_deck=deck == "smooth")
            x = sp.x_m
            dyn_part = 0.0 if excess is None else weight * excess[window.on_span]
            deltas.append(-sp.y_m - dyn_part)
            loads.append(float(weight))
        keys = tuple((e.data.vehicle_id, e.data.pass_id) for e in entries)
        return PassDeflections(np.asarray(x, dtype=float), keys, tuple(deltas), tuple(loads))
