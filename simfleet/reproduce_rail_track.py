"""Diagnosis of a rail batch's track D1 (EN 13848, 3–25 m) against the true track: which part of
the truth, substituted, removes the error.

A simulated batch (``driveby sim rail-track-prior --out DIR --passes N``) is calibrated as the cloud
does (:func:`cloud.rail.calibration.calibrate_batch`), and the fleet-mean AP's D1 is scored against
the true unloaded rail's with, in turn, the truth's common speed scale, every run's true speed, the
carriage's true parameters, and one best-fitting stretch and shift of the chainage (the fleet's own
frame) put in its place; with fewer runs of the batch too. Only this diagnosis reads the truth; the
cloud never does.

Run: ``python -m simfleet.reproduce_rail_track DIR [--runs 7,14,28]`` (one JSON line per batch size).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from cloud.rail.calibration import calibrate_batch
from cloud.rail.records import RailRun
from shared.dynamics.population import population_aps
from shared.track_quality import d1_longitudinal_level

from .reproduce_rail import load_runs

GRID_M = 0.05  # the truth's spacing, and the fleet mean's
GAMMA = 0.8  # the edge's inverse (and the calibration's): Newmark γ
BRIDGE_CLEARANCE_M = 5.0  # "off the bridge": this far from either end of the span
#: The stretch and shift searched for the fleet's frame (relative, m): wider than a batch's speed
#: scale error (the GNSS mean's, 2 %/√runs) and its chainage shifts.
STRETCHES = np.linspace(-0.012, 0.012, 49)
SHIFTS_M = np.linspace(-1.0, 1.0, 41)


def fleet_mean(runs: Sequence[RailRun], params: Sequence[dict], speeds: Sequence[float], x0_m: Sequence[float],
               length_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The mean AP of every run's four wheels, each run inverted under ``params`` and keyed in
    chainage with its ``speeds`` and first-sample chainage ``x0_m``, a cubic removed per wheel as
    the calibration does; on the route's grid (NaN where no wheel reached)."""
    grid = np.arange(0.0, length_m + 1e-9, GRID_M)
    total = np.zeros_like(grid)
    count = np.zeros_like(grid)
    for run, p, v, x0 in zip(runs, params, speeds, x0_m):
        aps, offsets = population_aps("carriage", [p], run.channels, run.dt, gamma=GAMMA)
        t = np.arange(aps.shape[1]) * run.dt
        for i in range(aps.shape[2]):
            x = x0 + v * t + offsets[0][i]
            sel = (grid >= x[0]) & (grid <= x[-1])
            y = np.interp(grid[sel], x, aps[0][:, i])
            total[sel] += y - np.polyval(np.polyfit(grid[sel], y, 3), grid[sel])
            count[sel] += 1
    return grid, np.where(count > 0, total / np.maximum(count, 1), np.nan)


def d1_errors(grid: np.ndarray, z: np.ndarray, truth: dict, exclude: tuple[float, float] | None = None,
              stretch: float = 0.0, shift_m: float = 0.0) -> tuple[float, float]:
    """rms(D1 − D1_true)/rms(D1_true) and sd(D1)/sd(D1_true) − 1 of the profile ``z`` on ``grid``
    (read at ``grid·(1 + stretch) + shift_m`` in the true frame), outside ``exclude`` (m)."""
    p = truth["profile"]
    xt = p["start_m"] + p["spacing_m"] * np.arange(len(p["elevation_m"]))
    ok = np.isfinite(z)
    g = grid[ok]
    d = d1_longitudinal_level(z[ok], GRID_M)
    if stretch or shift_m:
        d = np.interp(g, g * (1.0 + stretch) + shift_m, d, left=np.nan, right=np.nan)
    dt = d1_longitudinal_level(np.interp(g, xt, p["elevation_m"]), GRID_M)
    k = np.isfinite(d) & np.isfinite(dt)
    if exclude is not None:
        k &= (g < exclude[0]) | (g > exclude[1])
    return (float(np.sqrt(np.mean((d[k] - dt[k]) ** 2) / np.mean(dt[k] ** 2))),
            float(d[k].std() / dt[k].std() - 1.0))


def fleet_frame(grid: np.ndarray, z: np.ndarray, truth: dict, exclude=None) -> tuple[float, float, float]:
    """The error after the best single stretch and shift (the fleet's frame against the true one):
    (error, stretch, shift m)."""
    best = (math.inf, 0.0, 0.0)
    for s in STRETCHES:
        for sh in SHIFTS_M:
            e = d1_errors(grid, z, truth, exclude, s, sh)[0]
            if e < best[0]:
                best = (e, float(s), float(sh))
    return best


def diagnose(sim_dir: Path, n_runs: Sequence[int]) -> list[dict]:
    """One row per batch size: the batch's speed scale and lengths against the truth, and the D1
    error of the fleet mean under each substitution (module docstring)."""
    truth = json.loads((Path(sim_dir) / "truth.json").read_text())
    runs, cls, bridge = load_runs(Path(sim_dir))
    length = truth["route"]["length_m"]
    exclude = None
    if bridge is not None:
        exclude = (bridge.start_chainage_m - BRIDGE_CLEARANCE_M,
                   bridge.start_chainage_m + bridge.span_m + BRIDGE_CLEARANCE_M)
    true = {p["pass_id"]: p for p in truth["passes"]}
    car = truth["vehicles"]["car-0001"]
    rows = []
    for n in n_runs:
        batch = runs[:n]
        t0 = time.perf_counter()
        window = None if bridge is None else (-math.inf, bridge.start_chainage_m - 10.0)  # as the cloud
        fit = calibrate_batch(batch, cls.mean, cls.std, window_m=window)
        est = {r.pass_id: r for r in fit.runs}
        v_true = np.array([true[r.pass_id]["v"] for r in batch])
        v_cal = np.array([est[r.pass_id].mean["v"] for r in batch])
        scale = float(np.mean(np.log(v_cal / v_true)))
        cal = [{**cls.mean, **fit.globals_, **{k: est[r.pass_id].mean[k] for k in ("mv", "Iv", "v")}} for r in batch]
        exact = [{**cls.mean, **car, **{k: true[r.pass_id][k] for k in ("mv", "Iv", "v")}} for r in batch]
        x0 = [r.x0_m + est[r.pass_id].shift_m for r in batch]
        cases = {
            "calibrated": fleet_mean(batch, cal, v_cal, x0, length),
            "calibrated, common speed scale true": fleet_mean(batch, cal, v_cal * math.exp(-scale),
                                                                [x * math.exp(-scale) for x in x0], length),
            "calibrated parameters, true speeds": fleet_mean(batch, cal, v_true, [0.0] * n, length),
            "true parameters, calibrated speeds": fleet_mean(batch, exact, v_cal, x0, length),
            "true parameters, true speeds": fleet_mean(batch, exact, v_true, [0.0] * n, length),
        }
        row = {"runs": n, "fit_s": round(time.perf_counter() - t0, 1),
               "speed_scale_error_pct": round(100 * scale, 3),
               "speed_ratio_sd_pct": round(100 * float(np.std(np.log(v_cal / v_true))), 4),
               "Lv_error_pct": round(100 * (fit.globals_["Lv"] / car["Lv"] - 1), 3)}
        for name, (grid, z) in cases.items():
            e, sd = d1_errors(grid, z, truth)
            r = {"d1_error_pct": round(100 * e, 2), "d1_sd_error_pct": round(100 * sd, 2)}
            if exclude is not None:
                r["off_bridge_pct"] = round(100 * d1_errors(grid, z, truth, exclude)[0], 2)
            if name == "calibrated":
                e_f, s, sh = fleet_frame(grid, z, truth, exclude)
                r.update(fleet_frame_pct=round(100 * e_f, 2), stretch_pct=round(100 * s, 3), shift_m=round(sh, 3))
            row[name] = r
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m simfleet.reproduce_rail_track", description=__doc__.split("\n")[0])
    p.add_argument("sim_dir", type=Path, help="a simulated rail batch (driveby sim rail-... --out DIR)")
    p.add_argument("--runs", default="", help="batch sizes, comma-separated (default: the whole batch)")
    args = p.parse_args(argv)
    n_all = len(json.loads((args.sim_dir / "truth.json").read_text())["passes"])
    sizes = [int(s) for s in args.runs.split(",") if s] or [n_all]
    for row in diagnose(args.sim_dir, sizes):
        print(json.dumps(row), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
