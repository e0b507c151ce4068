"""Fleet self-calibration, the coordinator: alternate "profile given vehicles" with "vehicles
given profile" as passes arrive, and publish each vehicle's calibration when it moves.

The profile step is exact and incremental (the profile estimator). The vehicle step
(:mod:`cloud.calibration`) fits each vehicle to the consensus of the *others* (leave-one-out, so a
vehicle cannot confirm itself). Alternation converges slowly along one direction: the whole
fleet's parameters drifting together (the consensus inherits the fleet's common bias). The
coordinator therefore over-relaxes the fleet-mean part of each round's change, which removes most
of that slow mode, while each vehicle's own deviation is taken as fitted.
"""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np

from shared.registry import Site
from shared.schema import ApSegment, Calibration

from .calibration import (REFERENCE, PassAp, VehicleFit, calibration_names, class_prior, fit_vehicle,
                          from_calibration, to_calibration)

log = logging.getLogger(__name__)

MAX_STEP = 0.15  # largest change of any log-quantity in one round (≈ 16 %)


@dataclasses.dataclass
class VehicleState:
    model: str
    version: int
    params: dict
    fit: VehicleFit | None = None
    history: list = dataclasses.field(default_factory=list)  # (round, names, mean, lo, hi)


class FleetCalibrator:
    """Decides and computes calibration rounds; the daemon publishes what :meth:`round` returns."""

    def __init__(self, site: Site, estimator, tol: float = 3e-3, max_rounds: int = 12, relax: float = 3.0,
                 min_passes: int = 3):
        self.site, self.estimator = site, estimator
        self.tol, self.max_rounds, self.relax, self.min_passes = tol, max_rounds, relax, min_passes
        self.vehicles: dict[str, VehicleState] = {}
        self.rounds = 0
        self.settled = True
        self.dirty = False  # new data since the last round

    def initial(self, vehicle_id: str, model: str) -> VehicleState:
        st = self.vehicles.get(vehicle_id)
        if st is None:
            mean = dict(self.site.vehicle_class(model).mean)
            st = self.vehicles[vehicle_id] = VehicleState(model, 0, mean)
        return st

    def note_pass(self, vehicle_id: str, model: str) -> None:
        """A pass was completed: the fleet may need another round."""
        self.initial(vehicle_id, model)
        self.dirty, self.settled = True, False

    def ready(self, segments: dict) -> bool:
        """A round may run when every held segment is at its vehicle's current calibration."""
        if not self.dirty or self.rounds >= self.max_rounds:
            return False
        for seg in segments.values():
            st = self.vehicles.get(seg.vehicle_id)
            if st is not None and seg.calib_version != st.version:
                return False
        return len({s.pass_id for s in segments.values()}) >= self.min_passes

    def round(self, segments: dict[tuple, ApSegment]) -> list[Calibration]:
        """One vehicle step for every vehicle with data; returns the calibrations that changed."""
        by_vehicle: dict[str, list[ApSegment]] = {}
        for seg in segments.values():
            by_vehicle.setdefault(seg.vehicle_id, []).append(seg)
        steps: dict[str, tuple[np.ndarray, VehicleFit]] = {}
        for vid, segs in sorted(by_vehicle.items()):
            st = self.vehicles.get(vid)
            if st is None or st.model not in REFERENCE:
                continue
            fit = self._vehicle_step(st, segs)
            if fit is None:
                continue
            current = np.log([to_calibration(st.model, st.params)[n] for n in fit.names])
            steps[vid] = (np.log(fit.mean) - current, fit)
        self.rounds += 1
        self.dirty = False
        if not steps:
            self.settled = True
            return []
        by_model: dict[str, list[np.ndarray]] = {}
        for vid, (delta, _) in steps.items():
            by_model.setdefault(self.vehicles[vid].model, []).append(delta)
        common = {m: np.mean(ds, axis=0) for m, ds in by_model.items()}
        out = []
        biggest = 0.0
        for vid, (delta, fit) in steps.items():
            st = self.vehicles[vid]
            relax = self.relax if self.rounds > 1 else 1.0  # the first round has no trend to extrapolate
            # A trust region: no quantity moves by more than MAX_STEP (in log) per round, so one
            # bad fit (a misaligned pass, a wild start) cannot throw a vehicle far off.
            step = np.clip(delta + (relax - 1.0) * common[st.model], -MAX_STEP, MAX_STEP)
            biggest = max(biggest, float(np.max(np.abs(step))))
            st.fit = fit
            if np.max(np.abs(step)) < self.tol:
                continue
            ref, _ = REFERENCE[st.model]
            current = np.array([to_calibration(st.model, st.params)[n] for n in fit.names])
            new = dict(zip(fit.names, current * np.exp(step)))
            st.params = from_calibration(st.model, new, st.params[ref])
            st.version += 1
            st.history.append((self.rounds, fit.names, np.array(list(new.values())), fit.lo95, fit.hi95))
            out.append(Calibration(vehicle_id=vid, version=st.version, vehicle_model=st.model,
                                   params=st.params, source="fleet"))
        self.settled = not out or self.rounds >= self.max_rounds
        self.dirty = bool(out)
        log.info("calibration round %d: %d vehicles moved, largest log-step %.4f", self.rounds, len(out), biggest)
        return out

    def _vehicle_step(self, st: VehicleState, segs: list[ApSegment]) -> VehicleFit | None:
        for s in segs:
            self.estimator.retract(s)
        try:
            snaps = self.estimator.snapshot()
        finally:
            for s in segs:
                self.estimator.update(s)
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
            items.append((PassAp(lo, ss[0].spacing_m, vals, ss[0].speed_mps), np.repeat(cons[:, None], n_axles, 1)))
        if not items:
            return None
        cls = self.site.vehicle_class(st.model)
        ref, _ = REFERENCE[st.model]
        try:
            return fit_vehicle(st.model, st.params, items, class_prior(st.model, cls.mean, cls.std), st.params[ref])
        except (ValueError, np.linalg.LinAlgError, FloatingPointError) as e:
            log.warning("vehicle step failed: %s", e)
            return None

    def table(self) -> list[dict]:
        """Rows of ``vehicles.parquet``: vehicle_id, param, mean, lo95, hi95."""
        rows = []
        for vid, st in sorted(self.vehicles.items()):
            if st.fit is None:
                continue
            cal = to_calibration(st.model, st.params)
            for i, n in enumerate(st.fit.names):
                # Interval from the last vehicle step, centred on the published value.
                lo = cal[n] * st.fit.lo95[i] / st.fit.mean[i]
                hi = cal[n] * st.fit.hi95[i] / st.fit.mean[i]
                rows.append({"vehicle_id": vid, "param": n, "mean": cal[n], "lo95": lo, "hi95": hi})
        return rows


__all__ = ["FleetCalibrator", "calibration_names", "math"]
