"""Fleet self-calibration, the coordinator: a vehicle step for the fleet whenever new passes are
in, and each vehicle's calibration published when it moves.

Two vehicle steps, by model (:data:`PER_VEHICLE`):

* **joint** (sprung masses): every vehicle of a model fitted at once with the road
  profile profiled out (:func:`cloud.road.calibration.fit_fleet`). That solves "profile given
  vehicles" inside the step, so a round from the class prior lands near the answer: no local
  minima of a per-vehicle fit, no slow alternation. The edges then recompute their segments;
  the next round, on those, confirms (the remap is exact only up to the grid and each pass's
  unknown start, so a vehicle moves only by more than a fraction of its posterior spread, and a
  move that reverses the last one is halved).
* **per vehicle** (quarter-cars, half-cars): each vehicle against the leave-one-out consensus of the profile
  estimator, in acceleration space (:func:`cloud.road.calibration.fit_vehicle`), alternating with the
  exact profile step; the fleet-wide common part of each round's change is over-relaxed (for
  :data:`OVER_RELAXED` models), which
  removes most of alternation's slow mode (the whole fleet drifting together), and frozen for a
  quantity whose common change does not shrink as the fleet steps along it (the alternation cannot
  follow it: see :meth:`FleetCalibrator._common_relaxation`), judged on the rounds of the current
  passes only (:meth:`FleetCalibrator._trend`). A vehicle moves only by more than a
  fraction of its posterior spread, so that the fleet settles by tolerance.

The fleet-common mode (every vehicle's ratio off by the same factor) *is* identified by the data,
not only by the class prior: vehicles at different speeds (and with different resonances) see a
common change of a ratio at different wavelengths, which no single profile absorbs. The Fisher
information of the common log-offset of each ratio, the profile marginalised under its random-walk
prior (Whittle approximation), is far larger than the class prior's: for a fleet like road-qc's
(30 passes, 15–22 m/s, 2 % noise) the data alone pin it to a few hundredths of a per cent against
the prior's 2.6 % (14 % / √30), even with the road's spectrum left free at every frequency (so from
the passes' disagreement alone). A common error that stays is therefore a *model* bias every
vehicle shares: a discrete inverse and vehicle step add numerical damping that, against the
continuous physics, moves a quarter-car's fit by several per cent at Newmark γ = 0.8 and 2 ms
(c/M −4.4 %, m/M +4.7 %, k/M +6.8 %, noise-free, true profile) and by one to two per cent at the
edge's γ = 0.6. So quarter-car rounds run on continuous-time APs (the cloud corrects each pass,
CloudSettings.continuous_aps; the step reconstructs and predicts at γ ½, unbiased to 0.25 %,
tests/test_discretisation.py); the common error that remains is not the step's model.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import logging
import math
import time
from collections.abc import Generator

import numpy as np

from shared.registry import Site
from shared.schema import ApSegment, Calibration

from cloud.road.calibration import (REFERENCE, REMAP_DT, ConsensusSensitivity, PassAp, VehicleFit, calibration_names,
                                    class_prior, fit_fleet, fit_vehicle, from_calibration, to_calibration)
from cloud.road.continuous import CONTINUOUS_MODELS, continuous_ap_resampled, pass_speed, pass_values
from cloud.road.long_wave import pass_error_draws
from cloud.road.mean_profile import MeanProfile

log = logging.getLogger(__name__)

MAX_STEP = 0.5  # largest change of any log-quantity in one round (×1.6)
SIGNIFICANT = 0.25  # a vehicle moves when some quantity changes by more than this many posterior sd
MIN_CONTRACTION = 0.1  # a common mode whose change falls by less than this per unit step is frozen
#: The contraction is judged only once the common steps taken span at least this share of the largest
#: common change seen: over a shorter lever the line's slope is the rounds' scatter (a first round's
#: step gated to a few tenths of a per cent against changes of a few per cent), and its sign freezes
#: a mode that would have contracted, where the first round left it.
MIN_LEVER = 0.5
TREND_ROUNDS = 24  # refinements remembered for the common-mode trend
REFINE_STEP = 0.15  # largest change of any log-quantity in one per-vehicle round (≈ 16 %)
CONSENSUS_DRAWS = 16  # draws of the consensus's error an exported interval's errors-in-variables term is made of
SLOW_ITERATIONS = 2  # subspace iterations that pick the fleet's slow modes out (FleetCalibrator._fixed_point)
#: the least contraction per round a slow mode is taken at (below it the class prior, which each
#: vehicle's fit carries, pins the mode, and the linearisation would amplify it without bound)
MIN_SLOW = 0.05
#: Models calibrated per vehicle in acceleration space against the leave-one-out consensus (sensor
#: noise is white there). For a quarter-car fleet at 2 % noise that is more accurate than the joint
#: AP-space step, whose AP misfit the inverse's noise amplification at short wavelengths weighs
#: wrongly; for half-cars, whose AP is mostly that amplified noise, far more so (see
#: :data:`cloud.road.calibration.REMAP_SETTINGS` and :data:`CONTINUOUS_CONSENSUS`).
PER_VEHICLE = frozenset({"quarter_car", "half_car"})
#: Per-vehicle models whose fleet-common change is over-relaxed (:meth:`FleetCalibrator._common_relaxation`).
#: Not half-cars: their common change then grows round on round, every round at the step limit,
#: and the profile gets worse.
OVER_RELAXED = frozenset({"quarter_car"})
#: Per-vehicle models whose vehicle step runs against a consensus of continuous-time APs
#: (:func:`cloud.road.continuous.continuous_ap_resampled`: the edge inverse's discretisation undone per pass under
#: the vehicle's own parameters, in a copy of the profile estimator) and predicts with continuous
#: physics (``RemapSettings.predict_gamma`` ½). The edge's γ = 0.8 distorts each half-car's AP at
#: the wheel hop by its own parameters and speed (2–4 % of the road in 1.5 c/m – 30 m, noise-free);
#: against a blend of the others' distortions each vehicle's fit absorbs their difference.
CONTINUOUS_CONSENSUS = frozenset({"half_car"})
#: Per model not over-relaxed: the fraction of the fleet-common change a refinement applies. And
#: per-vehicle models whose refinement steps are halved at each reversal (as the joint step's).
#: Half-cars: with the full common change applied, the fleet swings round on round and does not
#: settle within the round budget; a fraction of it, with the reversal halving, settles and gives
#: the best ratios and profile (docs/results.md).
COMMON_GAIN = {"half_car": 0.3}
REVERSAL_DAMPED = frozenset({"half_car"})


@dataclasses.dataclass(frozen=True)
class _Coupled:
    """One vehicle's part in the fleet's coupling through the consensus (FleetCalibrator._fleet_error)."""

    sens: ConsensusSensitivity
    moves: np.ndarray  # (draws, quantities): its fit's moves under the consensus's error draws
    response: list  # per pass (quantities, points, contacts): its AP's change per log-change of its ratios
    where: list  # per pass: (route id, first grid index, end index, weights (points, contacts) in the consensus)
    n_axles: int
    last: np.ndarray  # its fit less its published ratios (log units): the change the rounds left
    speed: float  # m/s, its passes' mean


def _orthonormal(X: np.ndarray) -> np.ndarray:
    """An orthonormal basis of the columns of X (columns that add nothing dropped)."""
    q, r = np.linalg.qr(X)
    keep = np.abs(np.diag(r)) > 1e-9 * max(float(np.abs(np.diag(r)).max()), 1e-300)
    return q[:, keep]


@dataclasses.dataclass
class VehicleState:
    model: str
    version: int
    params: dict
    fit: VehicleFit | None = None
    last_step: np.ndarray | None = None  # the last published change of the log-quantities
    damping: float = 1.0  # fraction of the fitted change published (halved at each reversal)
    history: list = dataclasses.field(default_factory=list)  # (round, names, mean, lo, hi)


class FleetCalibrator:
    """Decides and computes calibration rounds; the daemon publishes what :meth:`round` returns."""

    def __init__(self, site: Site, estimator, tol: float = 3e-3, max_rounds: int = 12, relax: float = 3.0,
                 min_passes: int = 3):
        self.site, self.estimator = site, estimator  # the profile: leave-one-out consensus of a refinement
        self.last_round_s = 0.0  # wall time of the last round, s
        self.tol, self.max_rounds, self.relax, self.min_passes = tol, max_rounds, relax, min_passes
        self.refinements = 0  # refinement rounds run (the over-relaxation needs a trend)
        #: per model, per refinement: (common step taken before it, its common change, the common
        #: step it applied), log-units (see :meth:`_common_relaxation`)
        self.common_trend: dict[str, list[tuple[list, list, list]]] = {}
        #: per model: the fingerprint of the passes the trend was measured on (see :meth:`_trend`)
        self.trend_passes: dict[str, str] = {}
        self.vehicles: dict[str, VehicleState] = {}
        self.rounds = 0
        self.budget_from = 0  # the round count when the last new pass arrived
        self.settled = True
        self.dirty = False  # new data since the last round
        #: The segments a round is given are continuous-time APs for :data:`CONTINUOUS_MODELS`
        #: (the cloud corrected them, cloud.daemon.node): the vehicle step then reconstructs and predicts
        #: at γ ½ (:class:`cloud.road.calibration.PassRemap`) and needs no corrected copy of the consensus.
        self.continuous_aps = False
        #: (vehicle, pass) → the sample interval (s) the edge inverted the pass at (its pass-done; the
        #: daemon sets this before a round, as it sets ``estimator``); a pass not here was a 500 Hz log's.
        self.sample_intervals: dict[tuple[str, str], float] = {}
        #: Vehicle steps taken ahead of a round in bounded slices (:meth:`prepare`): the estimator they
        #: were taken against, per vehicle (its parameters' key, its fit), and per model the continuous
        #: consensus they used. Not state: a function of the round's data, dropped with the estimator.
        self._prepared: tuple[object, dict, dict] | None = None
        #: Per vehicle, its APs' response to its ratios as the last vehicle table built it (its inputs'
        #: key, the response): a function of the vehicle's parameters and passes alone, so most of a
        #: fleet's carries over from one table to the next. Shared with :meth:`snapshot`'s copies.
        self._responses: dict[str, tuple[str, list]] = {}

    # -- durable state (cloud/daemon/durable.py journals it after every round) --------------------
    def state(self) -> dict:
        """Everything a round depends on, as JSON-able data: a restarted cloud resumes mid-calibration."""
        def arr(x):
            return None if x is None else np.asarray(x, dtype=float).tolist()

        def fit(f):
            return None if f is None else {"names": list(f.names), "mean": arr(f.mean), "lo95": arr(f.lo95),
                                           "hi95": arr(f.hi95), "params": dict(f.params),
                                           "residual_m": float(f.residual_m), "n_points": int(f.n_points)}

        return {
            "rounds": self.rounds, "settled": self.settled, "dirty": self.dirty, "refinements": self.refinements,
            "budget_from": self.budget_from,
            "common_trend": {m: [[list(a), list(b), list(c)] for a, b, c in h] for m, h in self.common_trend.items()},
            "trend_passes": dict(self.trend_passes),
            "vehicles": {vid: {"model": st.model, "version": st.version, "params": dict(st.params), "fit": fit(st.fit),
                               "last_step": arr(st.last_step), "damping": st.damping,
                               "history": [[r, list(n), arr(m), arr(lo), arr(hi)] for r, n, m, lo, hi in st.history]}
                         for vid, st in self.vehicles.items()},
        }

    def load_state(self, state: dict) -> None:
        """The inverse of :meth:`state`."""
        def arr(x):
            return None if x is None else np.asarray(x, dtype=float)

        self.rounds, self.settled, self.dirty = int(state["rounds"]), bool(state["settled"]), bool(state["dirty"])
        self.refinements = int(state.get("refinements", 0))
        self.budget_from = int(state.get("budget_from", 0))
        self.common_trend = {m: [(list(a), list(b), list(c)) for a, b, c in h]
                             for m, h in state.get("common_trend", {}).items()}
        self.trend_passes = {m: str(k) for m, k in state.get("trend_passes", {}).items()}
        self.vehicles = {}
        for vid, v in state["vehicles"].items():
            f = v["fit"]
            fit = None if f is None else VehicleFit(names=list(f["names"]), mean=arr(f["mean"]), lo95=arr(f["lo95"]),
                                                    hi95=arr(f["hi95"]), params=dict(f["params"]),
                                                    residual_m=f["residual_m"], n_points=f["n_points"])
            self.vehicles[vid] = VehicleState(
                model=v["model"], version=int(v["version"]), params=dict(v["params"]), fit=fit,
                last_step=arr(v["last_step"]), damping=float(v["damping"]),
                history=[(r, list(n), arr(m), arr(lo), arr(hi)) for r, n, m, lo, hi in v["history"]])

    def initial(self, vehicle_id: str, model: str) -> VehicleState:
        st = self.vehicles.get(vehicle_id)
        if st is None:
            mean = dict(self.site.vehicle_class(model).mean)
            st = self.vehicles[vehicle_id] = VehicleState(model, 0, mean)
        return st

    def note_pass(self, vehicle_id: str, model: str, new: bool = True) -> None:
        """A pass was completed (``new``) or recomputed: the fleet may need another round.

        A new pass opens a fresh budget of ``max_rounds``: a daemon runs for months, and vehicles
        that join after the first rounds must be calibrated too; a recomputed one does not.
        """
        self.initial(vehicle_id, model)
        self.dirty, self.settled = True, False
        if new:
            self.budget_from = self.rounds

    @property
    def exhausted(self) -> bool:
        """The rounds since the last new pass have reached ``max_rounds``."""
        return self.rounds - self.budget_from >= self.max_rounds

    def ready(self, segments: dict) -> bool:
        """A round may run when every held segment is at its vehicle's current calibration."""
        if not self.dirty or self.exhausted:
            return False
        for seg in segments.values():
            st = self.vehicles.get(seg.vehicle_id)
            if st is not None and seg.calib_version != st.version:
                return False
        return len({s.pass_id for s in segments.values()}) >= self.min_passes

    def _groups(self, segments: dict[tuple, ApSegment]) -> tuple[dict, dict]:
        """A round's segments per vehicle, and per model its vehicles with usable passes (sorted)."""
        by_vehicle: dict[str, list[ApSegment]] = {}
        for seg in segments.values():
            by_vehicle.setdefault(seg.vehicle_id, []).append(seg)
        by_model: dict[str, list[tuple[str, list[PassAp]]]] = {}
        for vid, segs in sorted(by_vehicle.items()):
            st = self.vehicles.get(vid)
            if st is None or st.model not in REFERENCE:
                continue
            items = self._passes(segs, self.sample_intervals)
            if items:
                by_model.setdefault(st.model, []).append((vid, items))
        return by_vehicle, by_model

    @staticmethod
    def round_key(segments: dict[tuple, ApSegment], sample_intervals: dict) -> str:
        """A fingerprint of what a round's consensus and vehicle steps are made of (the segments, in
        order, and their passes' sample intervals): the vehicle steps :meth:`prepare` took hold for a
        round on segments of the same key, against a consensus built from them."""
        h = hashlib.sha1()
        for sl, seg in segments.items():
            h.update(repr((sl, seg.vehicle_id, seg.pass_id, seg.route_id, seg.axle, seg.start_index, seg.spacing_m,
                           seg.calib_version, seg.speed_mps,
                           sample_intervals.get((seg.vehicle_id, seg.pass_id)))).encode())
            h.update(np.ascontiguousarray(seg.values, dtype=float).tobytes())
            h.update(np.ascontiguousarray(seg.sigma, dtype=float).tobytes())
        return h.hexdigest()

    def prepare(self, segments: dict[tuple, ApSegment], work=None) -> bool:
        """Idle work ahead of a round on ``segments``: its per-vehicle models' vehicle steps, in the
        round's order, against ``estimator`` as the round would take them, as many as ``work`` allows
        (an object with ``more()`` and ``spent()``, as :class:`cloud.daemon.chainage.Slice`; None:
        all). True when every one is taken; :meth:`round` on the same segments and estimator then
        only applies them, so a round's work can be spread over many short calls with the same result.

        A step is a function of the vehicle's parameters, its segments and the estimator (the caller
        gives the same estimator object only for segments of the same :meth:`round_key`); a step whose
        vehicle's parameters changed meanwhile is taken again by :meth:`round`. Changes nothing the
        calibrator journals."""
        by_vehicle, by_model = self._groups(segments)
        if self._prepared is None or self._prepared[0] is not self.estimator:
            self._prepared = (self.estimator, {}, {})
        _, fits, conts = self._prepared
        for model, group in sorted(by_model.items()):
            if model not in PER_VEHICLE:
                continue
            vids = [vid for vid, _ in group]
            estimator, cont = self.estimator, {}
            if model in CONTINUOUS_CONSENSUS and not self._continuous(model):
                key = self._params_key(vids)
                if conts.get(model, (None,))[0] != key:
                    if work is not None and not work.more():
                        return False
                    conts[model] = (key, *self._continuous_estimator(model, vids, by_vehicle))
                    if work is not None:
                        work.spent()
                _, estimator, cont = conts[model]
            for vid in vids:
                key = self._step_key(model, vid, vids)
                if fits.get(vid, (None,))[0] == key:
                    continue
                if work is not None and not work.more():
                    return False
                fits[vid] = (key, self._vehicle_step(self.vehicles[vid], by_vehicle[vid], estimator, cont.get(vid)))
                if work is not None:
                    work.spent()
        return True

    def _params_key(self, vids: list[str]) -> str:
        return repr([(vid, sorted(self.vehicles[vid].params.items())) for vid in vids])

    def _step_key(self, model: str, vid: str, vids: list[str]) -> str:
        """What a prepared vehicle step depends on beyond the round's segments and estimator: the
        vehicle's parameters, and for a continuous consensus every vehicle's of the model."""
        if model in CONTINUOUS_CONSENSUS and not self._continuous(model):
            return self._params_key(vids)
        return self._params_key([vid])

    def round(self, segments: dict[tuple, ApSegment]) -> list[Calibration]:
        """One vehicle step for every model's vehicles with data; the calibrations that changed. The
        steps :meth:`prepare` took for these segments against this estimator are used as they are."""
        by_vehicle, by_model = self._groups(segments)
        prepared = self._prepared if self._prepared is not None and self._prepared[0] is self.estimator else None
        self._prepared = None
        self.rounds += 1
        self.dirty = False
        out = []
        biggest = 0.0
        t0 = time.perf_counter()
        for model, group in sorted(by_model.items()):
            cls = self.site.vehicle_class(model)
            prior = class_prior(model, cls.mean, cls.std)
            if model in PER_VEHICLE:
                moved, big = self._refine(model, [vid for vid, _ in group], by_vehicle, prior, prepared)
                out += moved
                biggest = max(biggest, big)
                continue
            try:
                fits = fit_fleet(model, [(self.vehicles[vid].params, items) for vid, items in group], prior)
            except (ValueError, np.linalg.LinAlgError, FloatingPointError) as e:
                log.warning("vehicle step failed for %s: %s", model, e)
                continue
            for (vid, _), fit in zip(group, fits):
                st = self.vehicles[vid]
                current = np.array([to_calibration(model, st.params)[n] for n in fit.names])
                # A trust region: one bad round (a misaligned pass, a wild start) cannot throw a
                # vehicle far off; the joint step normally lands well inside it.
                step = np.clip(np.log(fit.mean / current), -MAX_STEP, MAX_STEP)
                if st.last_step is not None and st.last_step.shape == step.shape and step @ st.last_step < 0:
                    # Reversing the last move: the remap is exact only up to the grid and the unknown
                    # start of each pass, so successive fits can straddle the optimum. Halving the
                    # steps at every reversal turns that cycle into a converging sequence.
                    st.damping *= 0.5
                step = st.damping * step
                biggest = max(biggest, float(np.max(np.abs(step))))
                st.fit = fit
                # Move only by what the data resolve: a change well inside the posterior's own
                # spread is round-to-round jitter, and publishing it would make every edge
                # recompute for nothing.
                se = np.log(fit.hi95 / fit.lo95) / (2 * 1.96)
                if st.version > 0 and np.all(np.abs(step) < np.maximum(self.tol, SIGNIFICANT * se)):
                    continue
                out.append(self._publish(vid, fit, current * np.exp(step), step))
        n_vehicles = sum(len(g) for g in by_model.values())
        self.last_round_s = time.perf_counter() - t0
        self.settled = not out or self.exhausted
        self.dirty = bool(out)
        log.info("calibration round %d: %d/%d vehicles moved, largest log-step %.4f, %.2f s (%.3f s/vehicle)",
                 self.rounds, len(out), n_vehicles, biggest, self.last_round_s,
                 self.last_round_s / max(n_vehicles, 1))
        return out

    def _publish(self, vid: str, fit: VehicleFit, values: np.ndarray, step: np.ndarray) -> Calibration:
        st = self.vehicles[vid]
        ref, _ = REFERENCE[st.model]
        new = dict(zip(fit.names, values))
        st.params = from_calibration(st.model, new, st.params[ref])
        st.last_step = step
        st.version += 1
        st.history.append((self.rounds, fit.names, np.array(list(new.values())), fit.lo95, fit.hi95))
        return Calibration(vehicle_id=vid, version=st.version, vehicle_model=st.model, params=st.params,
                           source="fleet")

    def _refine(self, model: str, vids: list[str], by_vehicle: dict, prior,
                prepared: tuple | None = None) -> tuple[list[Calibration], float]:
        """A refinement round for vehicles the joint step has placed: each vehicle against the
        leave-one-out consensus of the profile estimator, in acceleration space, the fleet-wide
        common part of the changes over-relaxed (alternation's slow mode is the fleet drifting
        together). ``prepared``: steps :meth:`prepare` took (used where their key still holds)."""
        self.refinements += 1
        self._start_round(model, vids, {s.pass_id for vid in vids for s in by_vehicle[vid]})
        steps = {}
        _, fits, conts = prepared if prepared is not None else (None, {}, {})
        estimator, cont = self.estimator, {}
        if model in CONTINUOUS_CONSENSUS and not self._continuous(model):
            if conts.get(model, (None,))[0] == self._params_key(vids):
                _, estimator, cont = conts[model]
            else:
                estimator, cont = self._continuous_estimator(model, vids, by_vehicle)
        for vid in vids:
            key, fit = fits.get(vid, (None, None))
            if key != self._step_key(model, vid, vids):
                fit = self._vehicle_step(self.vehicles[vid], by_vehicle[vid], estimator, cont.get(vid))
            if fit is not None:
                current = np.log([to_calibration(model, self.vehicles[vid].params)[n] for n in fit.names])
                steps[vid] = (np.log(fit.mean) - current, fit)
        if not steps:
            return [], 0.0
        common = np.mean([d for d, _ in steps.values()], axis=0)
        relax = (self._common_relaxation(model, common) if model in OVER_RELAXED
                 else np.full_like(common, COMMON_GAIN.get(model, 1.0)))
        out, biggest, applied = [], 0.0, []
        for vid, (delta, fit) in steps.items():
            st = self.vehicles[vid]
            step = np.clip(delta + (relax - 1.0) * common, -REFINE_STEP, REFINE_STEP)
            if model in REVERSAL_DAMPED:
                if st.last_step is not None and st.last_step.shape == step.shape and step @ st.last_step < 0:
                    st.damping *= 0.5  # as the joint step: a reversal halves this vehicle's later moves
                step = st.damping * step
            biggest = max(biggest, float(np.max(np.abs(step))))
            st.fit = fit
            # As in the joint step: a change well inside the vehicle's posterior spread is round-to-
            # round jitter (on a 3-D carpet the lanes keep every fit moving by ~1 %); publishing it
            # would make the edge recompute for nothing and the fleet never settle.
            se = np.log(fit.hi95 / fit.lo95) / (2 * 1.96)
            if np.all(np.abs(step) < np.maximum(self.tol, SIGNIFICANT * se)):
                applied.append(np.zeros_like(step))
                continue
            applied.append(step)
            current = np.array([to_calibration(model, st.params)[n] for n in fit.names])
            out.append(self._publish(vid, fit, current * np.exp(step), step))
        hist = self.common_trend.setdefault(model, [])
        before = (np.asarray(hist[-1][0]) + np.asarray(hist[-1][2])) if hist else np.zeros_like(common)
        hist.append((before.tolist(), common.tolist(), np.mean(applied, axis=0).tolist()))
        del hist[:-TREND_ROUNDS]  # a daemon runs for months: the trend of the recent rounds
        log.info("refinement %d (%s): common change %s, relaxation %s", self.refinements, model,
                 np.round(common, 4).tolist(), np.round(relax, 2).tolist())
        return out, biggest

    def _start_round(self, model: str, vids: list[str], pass_ids: set[str]) -> None:
        """Before a refinement on ``pass_ids``: when they are new (a larger epoch), the common-mode
        trend begins afresh (:meth:`_trend`) and, for :data:`REVERSAL_DAMPED` models, so do the
        vehicles' step halvings — they served to straddle the old passes' optimum; kept, a daemon
        that gets passes for months would move its half-cars ever more slowly."""
        if not self._trend(model, pass_ids) and model in REVERSAL_DAMPED:
            for vid in vids:
                self.vehicles[vid].damping, self.vehicles[vid].last_step = 1.0, None

    def _trend(self, model: str, pass_ids: set[str]) -> list:
        """The common-mode trend of ``model``, begun afresh when the round's passes are not those the
        trend was measured on.

        The trend is a line through the rounds' common changes against the common steps taken, and
        its target (where the change vanishes) belongs to the passes of the rounds: when the daemon
        moves to a larger epoch the target moves by a few per cent. A line through both epochs' rounds
        would read no contraction and freeze the common mode where the first epoch left it, near the class
        prior, so every vehicle would keep the class mean's own offset from the fleet.
        """
        key = hashlib.sha1("\n".join(sorted(pass_ids)).encode()).hexdigest()
        if self.trend_passes.get(model) != key:
            self.common_trend[model] = []
            self.trend_passes[model] = key
        return self.common_trend[model]

    def _common_relaxation(self, model: str, common: np.ndarray) -> np.ndarray:
        """The factor applied to the fleet-wide common part of this round's changes, per quantity.

        Alternating vehicle and profile steps moves the fleet's common mode (all vehicles together)
        by only a fraction ``g`` of what it should each round (the consensus follows the vehicles):
        from the second refinement on, the common part is over-relaxed by ``relax``. Over the
        rounds, the common change ``d`` should fall along the common steps taken, ``d ≈ d0 − g S``
        (``S`` their running sum); a least-squares line through all rounds so far measures ``g``.
        Where ``d`` does not fall as the steps accumulate (``g`` ≤ ``MIN_CONTRACTION``) the
        alternation cannot follow the common mode (lanes of a 3-D carpet make the passes disagree;
        each vehicle's fit against the others' consensus then loses gain, which the consensus amplifies, round after
        round): that quantity's common part is frozen where the first rounds left it, near the class
        prior. (Scaling by the measured ``1/g`` instead settles worse.)
        """
        hist = self.common_trend.setdefault(model, [])
        if hist and len(hist[-1][1]) != common.size:
            hist.clear()
        if not hist:  # the first has no trend to extrapolate
            return np.ones_like(common)
        relax = np.full_like(common, self.relax)
        S = np.array([h[0] for h in hist])  # cumulative common step before each round
        D = np.array([h[1] for h in hist])
        for j in range(common.size):
            s = np.append(S[:, j], S[-1, j] + hist[-1][2][j])
            d = np.append(D[:, j], common[j])
            if np.ptp(s) <= max(self.tol, MIN_LEVER * float(np.max(np.abs(d)))):
                continue  # no step to learn from yet
            g = -np.polyfit(s, d, 1)[0]
            relax[j] = 0.0 if g <= MIN_CONTRACTION else self.relax
        return relax

    def _dt(self, seg: ApSegment) -> float:
        """The sample interval (s) of ``seg``'s pass at the edge."""
        return self.sample_intervals.get((seg.vehicle_id, seg.pass_id), REMAP_DT)

    @staticmethod
    def _passes(segs: list[ApSegment], sample_intervals: dict | None = None) -> list[PassAp]:
        """A vehicle's held segments as one :class:`PassAp` per pass (all axles, its grid slice)."""
        passes: dict[str, list[ApSegment]] = {}
        for s in segs:
            passes.setdefault(s.pass_id, []).append(s)
        n_axles = max(s.axle for s in segs)
        items = []
        for ss in passes.values():
            lo, vals = pass_values(ss, n_axles)
            if (np.isfinite(vals).sum(axis=0) < 200).any():
                continue
            dt = (sample_intervals or {}).get((ss[0].vehicle_id, ss[0].pass_id), REMAP_DT)
            items.append(PassAp(lo, ss[0].spacing_m, vals, pass_speed(ss), dt))
        return items

    def _continuous(self, model: str) -> bool:
        """Whether a round's segments of ``model`` are continuous-time APs already."""
        return self.continuous_aps and model in CONTINUOUS_MODELS

    def _continuous_estimator(self, model: str, vids: list[str], by_vehicle: dict):
        """A copy of the profile estimator with ``vids``' segments replaced by their continuous-time
        APs (:func:`cloud.road.continuous.continuous_ap_resampled`, per pass under the vehicle's parameters), and
        those segments per vehicle."""
        est = copy.deepcopy(self.estimator)
        out = {}
        for vid in vids:
            st = self.vehicles[vid]
            passes: dict[str, list[ApSegment]] = {}
            for s in by_vehicle[vid]:
                passes.setdefault(s.pass_id, []).append(s)
            n_axles = max(s.axle for s in by_vehicle[vid])
            new = []
            for ss in passes.values():
                lo, vals = pass_values(ss, n_axles)
                try:  # (the resampled correction: the one the half-car's settings are tuned for)
                    fixed = continuous_ap_resampled(model, st.params, PassAp(lo, ss[0].spacing_m, vals,
                                                                             ss[0].speed_mps, self._dt(ss[0])))
                except (ValueError, np.linalg.LinAlgError) as e:
                    log.warning("continuous AP failed for %s: %s", vid, e)
                    fixed = vals
                for s in ss:
                    v = fixed[s.start_index - lo : s.end_index - lo, s.axle - 1]
                    if not np.all(np.isfinite(v)):
                        v = np.where(np.isfinite(v), v, s.values)
                    c = ApSegment.make(v, s.sigma, vehicle_id=s.vehicle_id, pass_id=s.pass_id, route_id=s.route_id,
                                       tile=s.tile, axle=s.axle, start_index=s.start_index, spacing_m=s.spacing_m,
                                       calib_version=s.calib_version, speed_mps=s.speed_mps, t_first=s.t_first,
                                       t_last=s.t_last, seq=s.seq, n_segments_in_pass=s.n_segments_in_pass,
                                       flags=s.flags, error_model=s.error_model)
                    est.retract(s)
                    est.update(c)
                    new.append(c)
            out[vid] = new
        return est, out

    def _vehicle_step(self, st: VehicleState, segs: list[ApSegment], estimator=None,
                      held: list[ApSegment] | None = None) -> VehicleFit | None:
        """``estimator``: the profile the consensus comes from (default this calibrator's), holding
        ``held`` for the vehicle's own segments (default ``segs``)."""
        estimator = self.estimator if estimator is None else estimator
        held = segs if held is None else held
        for s in held:
            estimator.retract(s)
        try:
            snaps = estimator.snapshot()
        finally:
            for s in held:
                estimator.update(s)
        passes: dict[str, list[ApSegment]] = {}
        for s in segs:
            passes.setdefault(s.pass_id, []).append(s)
        items = []
        n_axles = max(s.axle for s in segs)
        for ss in passes.values():
            snap = snaps.get(ss[0].route_id)
            if snap is None:
                continue
            lo, hi = min(s.start_index for s in ss), max(s.end_index for s in ss)
            hi = min(hi, snap.elevation_m.size)
            vals = np.full((hi - lo, n_axles), np.nan)
            for s in ss:
                n = min(s.end_index, hi) - s.start_index
                vals[s.start_index - lo : s.start_index - lo + n, s.axle - 1] = s.values[:n]
            cons = snap.elevation_m[lo:hi]
            if np.isfinite(cons).sum() < 200 or np.isfinite(vals).all(axis=1).sum() < 200:
                continue
            # The consensus under each axle: the same route profile, seen at each axle's position.
            items.append((PassAp(lo, ss[0].spacing_m, vals, ss[0].speed_mps, self._dt(ss[0])),
                          np.repeat(cons[:, None], n_axles, 1)))
        if not items:
            return None
        cls = self.site.vehicle_class(st.model)
        ref, _ = REFERENCE[st.model]
        try:
            return fit_vehicle(st.model, st.params, items, class_prior(st.model, cls.mean, cls.std), st.params[ref],
                               ap_gamma=0.5 if self._continuous(st.model) else None)
        except (ValueError, np.linalg.LinAlgError, FloatingPointError) as e:
            log.warning("vehicle step failed: %s", e)
            return None

    def table(self, segments: list[ApSegment] | None = None) -> list[dict]:
        """Rows of ``vehicles.parquet``: vehicle_id, param, mean, lo95, hi95.

        The interval is centred on the published value. For per-vehicle models it carries, beside the
        last vehicle step's own Laplace spread, what that step takes as known (:meth:`_fleet_error`,
        from ``segments``, the held segments as the vehicle step sees them; without them, the step's
        spread alone): the consensus it was fitted against, and the part of that error every vehicle
        shares."""
        steps = self.table_steps(segments)
        while True:
            try:
                next(steps)
            except StopIteration as done:
                return done.value

    def table_steps(self, segments: list[ApSegment] | None = None) -> Generator[None, None, list[dict]]:
        """:meth:`table` one vehicle's linearisation at a time: a generator that yields between them and
        returns the rows, so that the caller can spread the work over bounded calls. It reads the
        calibrator as it is at each step: to build the table of one moment while rounds go on, run it
        on a :meth:`snapshot`."""
        rows = []
        extra = yield from self._fleet_error(segments or [])
        for vid, st in sorted(self.vehicles.items()):
            if st.fit is None:
                continue
            cal = to_calibration(st.model, st.params)
            se = np.log(st.fit.hi95 / st.fit.lo95) / (2 * 1.96)
            if vid in extra and extra[vid].shape == se.shape:
                se = np.sqrt(se**2 + extra[vid])
            for i, n in enumerate(st.fit.names):
                rows.append({"vehicle_id": vid, "param": n, "mean": cal[n], "lo95": cal[n] * math.exp(-1.96 * se[i]),
                             "hi95": cal[n] * math.exp(1.96 * se[i])})
        return rows

    def snapshot(self) -> FleetCalibrator:
        """A copy of the calibrator as it is now, for :meth:`table_steps` while this one goes on
        (the vehicles, the trend and the sample intervals copied; no estimator, nothing prepared)."""
        out = copy.copy(self)
        out.vehicles = copy.deepcopy(self.vehicles)
        out.common_trend = copy.deepcopy(self.common_trend)
        out.trend_passes = dict(self.trend_passes)
        out.sample_intervals = dict(self.sample_intervals)
        out.estimator, out._prepared = None, None
        return out

    def _fleet_error(self, segments: list[ApSegment],
                     n_draws: int = CONSENSUS_DRAWS) -> Generator[None, None, dict[str, np.ndarray]]:
        """Per vehicle of a :data:`PER_VEHICLE` model, the variance (log units) its step's Laplace
        interval leaves out (errors in variables), from the held ``segments`` (a generator: it
        yields before each vehicle's linearisation and returns the variances).

        * the consensus's own error: ``n_draws`` draws of it (the precision-weighted mean's stated
          error, with the passes' excess error, :func:`cloud.road.long_wave.pass_error_draws`), the
          same draws for every vehicle, each moving every vehicle's fit
          (:class:`cloud.road.calibration.ConsensusSensitivity`); each vehicle gets its own move's
          scatter about the fleet's mean move, plus that mean move (shared by every vehicle: it does
          not average out over the fleet) over the common mode's contraction ``g`` through the
          fleet's coupling (:meth:`_common_contraction`; the rounds' trend, :meth:`_contraction`,
          is their scatter over so few rounds, and where it reads a fast contraction it states a
          fleet at its fixed point that is not);
        * the distance the rounds stopped short of their fixed point, per vehicle. Every vehicle is
          fitted against a consensus the others' APs make, so the fits are coupled: a change ``x`` of
          the vehicles' log-ratios changes the consensus, which moves every fit by ``M x`` (both
          sides linearised at the published ratios). The rounds stop at ``θ`` where the fits still
          want to move by ``d`` (each vehicle's fit less its published ratios); the fixed point they
          were heading for lies ``(I − M)⁻¹ d`` away (:meth:`_fixed_point`). The fleet's slow modes
          (the vehicles' ratios moving together, in patterns their speeds and dynamics shape)
          contract by only a few per cent per round, far less than the common change's trend over
          the first, large rounds says, and a vehicle moves only by more than a fraction of its
          posterior spread, so the rounds stop while those modes are still far from settled;
        * a quantity whose common mode the rounds froze (its common change does not contract,
          :meth:`_contraction` at most :data:`MIN_CONTRACTION`) is not pinned by the data at all:
          its common part is then the class prior's for the mean of N vehicles, plus the distance
          the fleet's mean stands from the class mean, beside the scatter of the draws' moves.
        """
        by_vehicle: dict[str, list[ApSegment]] = {}
        for s in segments:
            st = self.vehicles.get(s.vehicle_id)
            if st is not None and st.fit is not None and st.model in PER_VEHICLE:
                by_vehicle.setdefault(s.vehicle_id, []).append(s)
        if not by_vehicle:
            return {}
        # The consensus the vehicle step compares against: the precision-weighted mean of the passes.
        consensus = MeanProfile({r.id: r.length_m for r in self.site.routes}, segments[0].spacing_m)
        for s in segments:
            if consensus.accepts(s):
                consensus.update(s)
        snaps = consensus.snapshot()
        rng = np.random.default_rng(0)  # an export is a function of the held segments
        draws = {}
        for rid, snap in snaps.items():
            held = [s for s in segments if s.route_id == rid]
            sd = np.nan_to_num((snap.hi95_m - snap.lo95_m) / (2 * 1.96))
            draws[rid] = sd * rng.standard_normal((n_draws, sd.size)) + np.nan_to_num(
                pass_error_draws(snap, held, n_draws, rng))
        out = {}
        by_model: dict[str, dict[str, _Coupled]] = {}
        for vid, vs in sorted(by_vehicle.items()):
            st = self.vehicles[vid]
            items, deltas, where = [], [], []
            n_axles = max(s.axle for s in vs)
            passes: dict[str, list[ApSegment]] = {}
            for s in vs:
                passes.setdefault(s.pass_id, []).append(s)
            for ss in passes.values():
                snap = snaps.get(ss[0].route_id)
                if snap is None:
                    continue
                lo, vals = pass_values(ss, n_axles)
                hi = min(lo + vals.shape[0], snap.elevation_m.size)
                vals = vals[: hi - lo]
                cons = snap.elevation_m[lo:hi]
                if np.isfinite(cons).sum() < 200 or np.isfinite(vals).all(axis=1).sum() < 200:
                    continue
                items.append((PassAp(lo, ss[0].spacing_m, vals, ss[0].speed_mps, self._dt(ss[0])),
                              np.repeat(cons[:, None], n_axles, 1)))
                deltas.append(np.repeat(draws[ss[0].route_id][:, lo:hi, None], n_axles, 2))
                # the pass's weight in the consensus (MeanProfile: 1/σ² per point, σ the segment's)
                sig = float(np.median(np.concatenate([np.asarray(s.sigma, float) for s in ss])))
                where.append((ss[0].route_id, lo, hi, np.isfinite(vals) / max(sig, 1e-12) ** 2))
            if not items:
                continue
            cls = self.site.vehicle_class(st.model)
            ref, _ = REFERENCE[st.model]
            yield  # a vehicle's linearisation is the unit of work
            try:
                sens = ConsensusSensitivity(st.model, st.params, items, class_prior(st.model, cls.mean, cls.std),
                                            st.params[ref], ap_gamma=0.5 if self._continuous(st.model) else None)
                moves = sens.moves(deltas)
                key = self._response_key(st, items)
                hit = self._responses.get(vid)
                response = hit[1] if hit is not None and hit[0] == key else sens.ap_response()
                self._responses[vid] = (key, response)
            except (ValueError, np.linalg.LinAlgError, FloatingPointError) as e:
                log.warning("consensus sensitivity failed for %s: %s", vid, e)
                continue
            current = np.log([to_calibration(st.model, st.params)[n] for n in st.fit.names])
            by_model.setdefault(st.model, {})[vid] = _Coupled(sens, moves, response, where, n_axles,
                                                              np.log(st.fit.mean) - current,
                                                              float(np.mean([it[0].speed_mps for it in items])))
        for model, coupled in by_model.items():
            vids = list(coupled)
            P = len(self.vehicles[vids[0]].fit.names)
            g = self._contraction(model, P)
            cls = self.site.vehicle_class(model)
            _, prior_sd = class_prior(model, cls.mean, cls.std)
            # Frozen: the class mean is the estimate of the fleet's mean, as the prior knows it, and the
            # fleet stands wherever the rounds left it: its distance from there is error too.
            names = self.vehicles[vids[0]].fit.names
            at_class = np.log([to_calibration(model, cls.mean)[n] for n in names])
            away = np.mean([np.log([to_calibration(model, self.vehicles[v].params)[n] for n in names]) - at_class
                            for v in vids], axis=0)
            frozen = g <= MIN_CONTRACTION
            moves = np.stack([coupled[v].moves for v in vids], axis=1)  # (draws, vehicles, quantities)
            common = moves.mean(axis=1)
            scatter = np.mean((moves - common[:, None, :]) ** 2, axis=0)
            # the distance to the fixed point the rounds were heading for, per vehicle
            last = np.stack([coupled[v].last for v in vids])
            try:
                solve = self._fixed_point(coupled, snaps)
                short = solve(last.reshape(1, -1)).reshape(len(vids), P)
                g_common = self._common_contraction(solve, len(vids), P, g)
            except (ValueError, np.linalg.LinAlgError, FloatingPointError) as e:
                log.warning("fleet fixed point failed for %s: %s", model, e)  # the common change over g, then
                short = np.broadcast_to(last.mean(axis=0) / np.maximum(g, MIN_CONTRACTION), last.shape)
                g_common = g
            # The draws' common move over the common mode's contraction through the coupling, not
            # carried through every slow mode: drawn white on the grid, the consensus's noise is far
            # larger at the body's wavelengths than the inverse's noise (sensor noise made blue) is,
            # so its move is already an upper bound; the other slow modes' amplification would
            # multiply that excess.
            var = scatter + np.mean(common**2, axis=0) / np.maximum(g_common, MIN_CONTRACTION) ** 2 + short**2
            var_frozen = scatter + prior_sd**2 / len(vids) + away**2
            log.debug("fleet error %s: contraction %s (rounds' trend %s), common move sd %s, common short %s, "
                      "rms short %s", model, np.round(g_common, 3), np.round(g, 3),
                      np.round(np.sqrt(np.mean(common**2, axis=0)), 5),
                      np.round(short.mean(axis=0), 5), np.round(np.sqrt(np.mean(short**2, axis=0)), 5))
            # A mode the data pin less than the class prior does is pinned by the prior (each fit carries
            # it): where the linearised distance exceeds the prior's statement, the prior's is the one.
            for k, vid in enumerate(vids):
                out[vid] = np.where(frozen, var_frozen[k], np.minimum(var[k], var_frozen[k]))
        return out

    def _response_key(self, st: VehicleState, items: list[tuple[PassAp, np.ndarray]]) -> str:
        """What :meth:`ConsensusSensitivity.ap_response` is a function of: the vehicle's parameters and
        step, and per pass its AP (and speed, grid, sample interval) and where its consensus has data
        (which sets the span the channels are rebuilt over)."""
        h = hashlib.sha1(repr((st.model, sorted(st.params.items()), self._continuous(st.model))).encode())
        for ap, cons in items:
            h.update(repr((ap.start_index, ap.spacing_m, ap.speed_mps, ap.dt_s, ap.values.shape)).encode())
            h.update(np.ascontiguousarray(ap.values, dtype=float).tobytes())
            h.update(np.isfinite(cons).tobytes())
        return h.hexdigest()

    def _fixed_point(self, coupled: dict[str, _Coupled], snaps: dict):
        """The operator ``r ↦ (I − M)⁻¹ r`` of :meth:`_fleet_error` on stacked per-vehicle log changes
        (rows of length vehicles × quantities), ``M`` the fleet's coupling through the consensus.

        ``M`` is applied, never formed (one forward run per pass and vehicle for each product): its
        slow subspace — the modes that contract least — is found by subspace iteration from the
        fleet's common and speed-graded modes (``M``'s other eigenvalues are small: one vehicle
        among many hardly moves the consensus, so those modes settle in a round or two and iteration
        picks the slow ones out within :data:`SLOW_ITERATIONS`), ``I − M`` solved there, and taken
        as the identity outside it. A slow mode contracting by less than :data:`MIN_SLOW` per round
        is taken at that contraction: such a mode is pinned by the class prior, not by the data."""
        vids = list(coupled)
        P = coupled[vids[0]].moves.shape[1]
        V = len(vids)
        # per route: each vehicle's passes' weights, summed (the consensus is their weighted mean)
        totals: dict[str, np.ndarray] = {}
        for c in coupled.values():
            for rid, lo, hi, w in c.where:
                t = totals.setdefault(rid, np.zeros(snaps[rid].elevation_m.size))
                t[lo:hi] += w.sum(axis=1)

        def apply_m(X: np.ndarray) -> np.ndarray:
            """``M`` on the columns of X (V·P, b)."""
            b = X.shape[1]
            xs = X.reshape(V, P, b)
            sums = {rid: np.zeros((b, t.size)) for rid, t in totals.items()}
            own = []
            for k, v in enumerate(vids):
                c = coupled[v]
                mine = []
                for (rid, lo, hi, w), resp in zip(c.where, c.response):
                    # this pass's AP change under each column's change of its vehicle's ratios
                    d = np.einsum("qnc,qb->bnc", resp, xs[k])
                    part = (d * w[None]).sum(axis=2)
                    sums[rid][:, lo:hi] += part
                    mine.append(part)
                own.append(mine)
            Y = np.zeros((V, P, b))
            for k, v in enumerate(vids):
                c = coupled[v]
                deltas = []
                for (rid, lo, hi, w), part in zip(c.where, own[k]):
                    loo = totals[rid][lo:hi] - w.sum(axis=1)  # the leave-one-out consensus's weight
                    change = (sums[rid][:, lo:hi] - part) / np.maximum(loo, 1e-300)[None, :]
                    deltas.append(np.repeat(np.where(loo > 0, change, 0.0)[:, :, None], c.n_axles, 2))
                Y[k] = c.sens.moves(deltas).T
            return Y.reshape(V * P, b)

        speed = np.array([coupled[v].speed for v in vids])
        graded = (speed - speed.mean()) / max(float(np.ptp(speed)), 1e-9)
        start = np.concatenate([np.kron(np.ones((V, 1)), np.eye(P)), np.kron(graded[:, None], np.eye(P))], axis=1)
        Q = _orthonormal(start)
        for _ in range(SLOW_ITERATIONS):
            Q = _orthonormal(apply_m(Q))
        MQ = apply_m(Q)
        JQ = np.eye(Q.shape[1]) - Q.T @ MQ
        u, sv, vt = np.linalg.svd(JQ)
        JQ_inv = vt.T @ np.diag(1.0 / np.maximum(sv, MIN_SLOW)) @ u.T

        def solve(R: np.ndarray) -> np.ndarray:
            R = np.atleast_2d(R)
            inside = R @ Q  # (rows, k)
            return R - inside @ Q.T + (inside @ JQ_inv.T) @ Q.T

        return solve

    @staticmethod
    def _common_contraction(solve, n_vehicles: int, n_quantities: int, fallback: np.ndarray) -> np.ndarray:
        """Per quantity, the fraction of a fleet-common change of it the rounds follow per round,
        through the fleet's linearised coupling (``solve``, :meth:`_fixed_point`): one over the
        common mode's amplification by ``(I − M)⁻¹``, clipped to at most 1; ``fallback`` where the
        coupling gives no positive amplification.

        Not the rounds' trend (:meth:`_contraction`): a line through a handful of rounds whose
        common steps are gated and clipped has their scatter for a slope (it reads anything from
        below zero to one for the same fleet's mode from seed to seed), while the coupling's
        contraction is a property of the fleet's speeds and dynamics and barely moves."""
        unit = np.tile(np.eye(n_quantities), (1, n_vehicles))  # row j: every vehicle's quantity j by 1
        amp = np.diag(solve(unit).reshape(n_quantities, n_vehicles, n_quantities).mean(axis=1))
        ok = np.isfinite(amp) & (amp > 0)
        return np.where(ok, np.minimum(1.0 / np.where(ok, amp, 1.0), 1.0), fallback)

    def _contraction(self, model: str, n: int) -> np.ndarray:
        """Per quantity, the fraction of a fleet-common change the rounds follow per round (the slope
        of the common change against the common steps taken, :meth:`_common_relaxation`), clipped to
        at most 1; 1 where the rounds give no trend."""
        hist = self.common_trend.get(model, [])
        g = np.ones(n)
        if len(hist) < 3 or len(hist[-1][1]) != n:
            return g
        S = np.array([h[0] for h in hist])
        D = np.array([h[1] for h in hist])
        for j in range(n):
            if np.ptp(S[:, j]) > self.tol:
                g[j] = min(-np.polyfit(S[:, j], D[:, j], 1)[0], 1.0)
        return g


__all__ = ["FleetCalibrator", "calibration_names"]
