"""The GNSS and carpet targets on small, fast versions of the scenarios: GNSS chainage error removed by aligning
each pass against the consensus; the 3-D carpet's fleet-mean profile under lane scatter.

Everything runs the daemons' cores (``edge.node.Edge``, ``cloud.daemon.core.Cloud``) wired by an in-memory
queue instead of Zenoh, sequenced as ``cloud.daemon.node.serve`` does when the bus is quiet: align, else
calibrate. Truth is read only here, to score.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

import pyarrow as pa
import pyarrow.parquet as pq

from cloud.daemon.node import Cloud
from cloud.daemon.settings import CloudSettings
from cloud.export import FLEET_FRAME, REGISTRY_FRAME
from cloud.road.alignment import FINE_BAND_M, estimate_alignment
from edge.chainage import ChainageTracker
from shared.drivelog import list_drive_logs, read_drive_log
from shared.schema import ApBatch, decode_ap
from simfleet.evaluate import load_truth, score_profile, score_vehicles
from simfleet.harness import Harness
from simfleet.reproduce import run_in_process
from simfleet.run import load_inputs
from simfleet.scenarios import SCENARIOS
from simfleet.sim import generate
from simfleet.worlds import ivp

SEED = 3


class Fleets:
    """Simulated fleets and their in-process runs, each made once for the module: several tests look
    at the same fleet (and the same run of it) from different sides, and none changes what it is given."""

    def __init__(self, tmp_path_factory):
        self._tmp = tmp_path_factory
        self._sims: dict[tuple, Path] = {}
        self._runs: dict[tuple, Cloud] = {}

    def simulate(self, name: str, passes: int, length_m: float, nominal: str = "true") -> Path:
        key = (name, passes, length_m, nominal)
        if key not in self._sims:
            out = self._tmp.mktemp(f"{name}-{nominal}")
            scenario = dataclasses.replace(SCENARIOS[name], route_length_m=length_m)
            generate(scenario, out, seed=SEED, passes=passes, vehicles=passes, nominal=nominal, workers=1,
                     progress=False)
            self._sims[key] = out
        return self._sims[key]

    def run(self, sim_dir: Path, calibration: str, align: bool | None = None, export: str = "export",
            ap_scale: float = 1.0) -> Cloud:
        """The logs through edge and cloud in process; ``align`` None: the cloud's default settings;
        ``ap_scale``: every AP the cloud receives multiplied by it (1: as the edge sent it)."""
        key = (sim_dir, calibration, align, export, ap_scale)
        if key not in self._runs:
            site, logs = load_inputs(sim_dir / "logs", sim_dir / "site.toml")
            settings = CloudSettings(calibration=calibration)
            if align is not None:
                settings = dataclasses.replace(settings, align=align)
            if ap_scale == 1.0:
                self._runs[key], _ = run_in_process(logs, site, sim_dir / export, settings=settings)
            else:
                self._runs[key] = _run_scaled(logs, site, sim_dir / export, settings, ap_scale)
        return self._runs[key]


def _run_scaled(logs, site, export_dir: Path, settings: CloudSettings, ap_scale: float) -> Cloud:
    """:func:`simfleet.harness.run_in_process` with every AP segment on the bus scaled by ``ap_scale``
    (its int16 codes kept, its scale and offset multiplied: the decoded values are the edge's times
    ``ap_scale``, to rounding)."""
    def scaled(key: str, payload: bytes) -> bool:
        if key.split("/")[2] != "ap":
            return False
        segs = [dataclasses.replace(s, scale_m=s.scale_m * ap_scale, offset_m=s.offset_m * ap_scale)
                for s in decode_ap(payload)]
        h.queue.append((key, ApBatch(tuple(segs)).encode()))
        return True

    h = Harness(site, settings, on_publish=scaled)
    h.replay(logs)
    h.settle()
    h.cloud.export(export_dir)
    return h.cloud


@pytest.fixture(scope="module")
def fleets(tmp_path_factory) -> Fleets:
    return Fleets(tmp_path_factory)


def _frames(export_dir) -> set[str]:
    return set(pq.read_table(export_dir / "profile.parquet").column("chainage_frame").to_pylist())


def _edge_chainage_maps(sim_dir):
    """pass_id → the edge's chainage as a function of true chainage (its tracker re-run on the log)."""
    passes = {p["pass_id"]: p for p in load_truth(sim_dir / "truth.json")["passes"]}
    maps = {}
    for path in list_drive_logs(sim_dir / "logs"):
        log = read_drive_log(path)
        p = passes[log.meta.pass_id]
        x_rep = ChainageTracker(1.0 / log.meta.sample_rate_hz).update(log.chainage, log.speed)
        x_true = p["true_chainage_at_start_m"] + p["speed_mps"] * log.t
        maps[log.meta.pass_id] = (x_true, x_rep)
    return maps


def _map_residuals(alignments, maps, x=np.linspace(15.0, 105.0, 7)) -> np.ndarray:
    """The cloud's chainage maps against the edge's (m), after the one affine frame F that fits best.

    The cloud places passes in the fleet's mean frame y = F(x_true), a shift and stretch away from
    the truth (all the data define): its map of pass p is C_p(y) = E_p(F⁻¹(y)) for the edge's map
    E_p. So C_p(F(x)) = E_p(x) for every pass with one F, fitted here by least squares (C_p is
    affine: α_p + β_p·y). Subtracting the passes' mean error at fixed points instead is exact only
    when F is near identity: it leaves (ε_p − ε̄)·(F⁻¹(x) − x), cm for a frame a metre off.
    """
    rows, rhs = [], []
    for (_, pid), al in alignments.items():
        alpha, beta = al.true_to_reported(0.0), 1.0 + al.stretch
        for xx, ee in zip(x, np.interp(x, *maps[pid])):
            rows.append([beta, beta * xx])
            rhs.append(ee - alpha)
    A, y = np.array(rows), np.array(rhs)
    f, *_ = np.linalg.lstsq(A, y, rcond=None)
    return A @ f - y


@pytest.mark.parametrize("nominal, rms_m, max_m", [
    ("true", 0.005, 0.012),  # measured 1.6 mm, 5.8 mm
    # Uncalibrated vehicles (the class mean in the logs), as the fleet calibration starts: their AP's
    # phase is wrong below ~2 m and placed passes 2.3 cm rms (3.9 cm max) off before the final fit
    # moved above wheel hop; a calibration learning from such passes was biased by 5-8 %.
    ("class", 0.010, 0.025),  # measured 3.8 mm, 11.2 mm
])
def test_alignment_places_every_pass_in_one_common_frame(fleets, nominal, rms_m, max_m):
    """12 passes, 120 m: every pass's chainage map (GNSS bias of metres, odometer stretch of ~1 %)
    is recovered to a few mm, up to the fleet's common frame, with the vehicles' true parameters and
    with the class mean."""
    gnss = fleets.simulate("road-qc-gnss", passes=12, length_m=120.0, nominal=nominal)
    cloud = fleets.run(gnss, "nominal")
    maps = _edge_chainage_maps(gnss)
    assert set(k[1] for k in cloud.alignments) == set(maps)
    truth = load_truth(gnss / "truth.json")
    raw = np.array([[p["gnss_bias_m"], p["speed_scale_error"]] for p in truth["passes"]])
    assert raw[:, 0].std() > 1.0 and raw[:, 1].std() > 0.005  # the errors to remove: metres and ~1 %
    err = _map_residuals(cloud.alignments, maps)
    print(f"chainage maps: residual rms {np.sqrt(np.mean(err**2)):.4f} m, max {np.abs(err).max():.4f} m")
    assert np.sqrt(np.mean(err**2)) < rms_m and np.abs(err).max() < max_m


def test_profile_with_gnss_error_is_as_good_as_without(fleets):
    """The GNSS target with true parameters: the aligned profile within 1.2x of the same fleet without
    GNSS error (alignment on the plain road changes nothing). Measured 1.94 % against 2.03 %.

    A loose guard on these 120 m records: the ratio is mostly the score's 5-50 m band near the ends
    (its band-pass pivots on the end values). With the drift nuisance off it is 1.36 % against
    1.01 % here and 1.10-1.71x over 7 seeds, though the passes are placed to 2 mm and an oracle
    alignment scores the same; padded about a line fitted over the last 2 m, 0.87-1.21x."""
    gnss = fleets.simulate("road-qc-gnss", passes=12, length_m=120.0)
    plain = fleets.simulate("road-qc", passes=12, length_m=120.0)
    fleets.run(gnss, "nominal")
    fleets.run(plain, "nominal")
    score = score_profile(gnss / "export", load_truth(gnss / "truth.json"), fit_frame=True).rel_error
    reference = score_profile(plain / "export", load_truth(plain / "truth.json")).rel_error
    print(f"profile {score:.4f} with GNSS error and alignment, {reference:.4f} without")
    assert score <= 1.2 * reference


def test_carpet_fleet_mean_profile_under_lane_scatter(fleets):
    """12 passes on random lanes of the 3-D carpet, true parameters: the fused profile is the fleet
    mean (the lane-count-weighted mean of the lanes driven) within 10 %, though single lanes differ
    from it by far more at short wavelengths."""
    carpet = fleets.simulate("carpet", passes=12, length_m=120.0)
    truth = load_truth(carpet / "truth.json")
    lanes = {p["lane"] for p in truth["passes"]}
    assert len(lanes) >= 4  # the passes really scatter across the carpet
    fleets.run(carpet, "nominal")
    score = score_profile(carpet / "export", truth).rel_error
    print(f"carpet fleet-mean profile error {score:.4f}")
    assert score <= 0.10


def _score_where_the_fleet_is(export_dir: Path, out_dir: Path, truth: dict, fit_frame: bool) -> float:
    """:func:`score_profile` of the exported profile where at least half the passes are.

    With GNSS bias of metres the passes start and end metres apart in true chainage, so the export's
    first and last metres hold one or two passes, which a fleet in one frame does not have; the
    score's band-pass pivots on its end values, so the first half-metre of one pass's noise sets its
    error over the next tens of metres (its 10 m trim does not reach that far). Scored where the
    fleet is, the two fleets' profiles are compared, not their ends."""
    table = pq.read_table(export_dir / "profile.parquet")
    n = np.asarray(table.column("n_passes"))
    out_dir.mkdir(parents=True, exist_ok=True)
    pq.write_table(table.filter(pa.array(n >= n.max() / 2)), out_dir / "profile.parquet")
    return score_profile(out_dir, truth, fit_frame=fit_frame).rel_error


def _export_frame_error(sim_dir, export_dir, x) -> tuple[np.ndarray, np.ndarray]:
    """(where the export puts true chainage ``x`` − x, where the fleet's mean reported chainage puts
    it − x), m: the first fitted from the exported profile against the true one, the second from the
    edges' chainage maps of the truth's passes."""
    maps = _edge_chainage_maps(sim_dir)
    fleet = np.mean([np.interp(x, *m) for m in maps.values()], axis=0)
    t = pq.read_table(export_dir / "profile.parquet").to_pydict()
    xe, est = np.asarray(t["chainage_m"]), np.asarray(t["elevation_m"])
    p = load_truth(sim_dir / "truth.json")["profile"]
    true = np.interp(xe, p["start_m"] + p["spacing_m"] * np.arange(len(p["elevation_m"])), p["elevation_m"])
    frame = estimate_alignment(xe, est, xe, true, max_shift_m=3.0, max_stretch=0.02, refine_band_m=FINE_BAND_M)
    assert frame is not None
    return frame.true_to_reported(x) - x, fleet - x


def test_default_run_with_gnss_error_is_as_good_as_without(fleets, tmp_path):
    """The GNSS target on a small version, with the cloud's *default* settings (fleet calibration,
    alignment on): the profile within 1.2x of the same fleet without GNSS error, scored in the
    fleet's frame where at least half the passes are (:func:`_score_where_the_fleet_is`), and the
    vehicles calibrated as well (k/M, c/M medians within 3 %). The frame is
    the fleet's mean frame — where the passes' reported chainage puts the road on average — and the
    export says so; the true frame is off by that mean (metres of GNSS bias and % of stretch over 12
    passes average to decimetres), which only a surveyed reference removes. Without alignment the
    calibration learns a smeared road and diverges."""
    gnss = fleets.simulate("road-qc-gnss", passes=12, length_m=120.0, nominal="class")
    plain = fleets.simulate("road-qc", passes=12, length_m=120.0, nominal="class")
    fleets.run(gnss, "fleet")
    fleets.run(plain, "fleet")
    truth, plain_truth = load_truth(gnss / "truth.json"), load_truth(plain / "truth.json")
    score = _score_where_the_fleet_is(gnss / "export", tmp_path / "gnss", truth, fit_frame=True)
    reference = _score_where_the_fleet_is(plain / "export", tmp_path / "plain", plain_truth, fit_frame=False)
    whole = score_profile(gnss / "export", truth, fit_frame=True).rel_error
    whole_reference = score_profile(plain / "export", plain_truth).rel_error
    true_frame = score_profile(gnss / "export", truth).rel_error
    ratios = score_vehicles(gnss / "export", truth)
    print(f"default run: profile {score:.4f} with GNSS error in the fleet's frame, {reference:.4f} without, where "
          f"half the fleet is ({whole:.4f}, {whole_reference:.4f} with the ends; {true_frame:.4f} in the true "
          "frame); ratio medians " + ", ".join(f"{k} {v[0] * 100:.2f} %" for k, v in ratios.items()))
    assert score <= 1.2 * reference
    assert ratios["k/M"][0] <= 0.03 and ratios["c/M"][0] <= 0.03
    assert _frames(gnss / "export") == {FLEET_FRAME}
    x = np.linspace(20.0, 100.0, 5)
    export_off, fleet_off = _export_frame_error(gnss, gnss / "export", x)
    print(f"frame: export − truth {np.round(export_off, 3)} m, fleet mean − truth {np.round(fleet_off, 3)} m")
    # The export's frame is the fleet's mean to a couple of cm (the fit of one profile against another
    # in the 0.5-5 m band), while that mean is decimetres off the truth: the frame the data define.
    assert np.max(np.abs(export_off - fleet_off)) < 0.02
    assert np.max(np.abs(fleet_off)) > 0.1


def test_default_run_with_gnss_error_does_not_amplify_rounding(fleets):
    """The default run of the GNSS fleet (fleet calibration interleaved with alignment sweeps) is a
    smooth function of its input: every AP multiplied by 1 + 1e-12 — the size of a change in the
    edge's rounding — moves the exported profile by a bounded amount, not onto another path.

    What it may move: the edge quantises each recomputed segment to int16 codes, so calibrations
    that differ at 1e-12 flip an occasional code, and the rounds carry that on (1e-5 of the
    profile's sd, measured). A discrete decision taken the other way (a point with or without data,
    a pass placed a grid point further) moves the profile by percent and the chainage grid itself."""
    gnss = fleets.simulate("road-qc-gnss", passes=12, length_m=120.0, nominal="class")
    fleets.run(gnss, "fleet")
    fleets.run(gnss, "fleet", export="export-scaled", ap_scale=1.0 + 1e-12)
    a, b = (pq.read_table(gnss / e / "profile.parquet").to_pydict() for e in ("export", "export-scaled"))
    assert a["chainage_m"] == b["chainage_m"] and a["n_passes"] == b["n_passes"]
    ea, eb = np.asarray(a["elevation_m"]), np.asarray(b["elevation_m"])
    moved = np.max(np.abs(eb - ea)) / np.std(ea)
    print(f"largest move of the profile under a 1e-12 change of the APs: {moved:.1e} of its sd")
    assert moved < 1e-3  # 100x the code flips' measured effect; a different path moves it by percent


def test_alignment_on_by_default_is_a_no_op_on_a_fleet_in_one_frame(fleets):
    """Clean data are not made worse by alignment being on: a fleet without GNSS error is aligned (every
    pass is looked at), nothing moves by more than ``align_apply_m``, and the export is the one without
    alignment, its chainage in the registry's frame."""
    plain = fleets.simulate("road-qc", passes=12, length_m=120.0)
    cloud = fleets.run(plain, "nominal")
    fleets.run(plain, "nominal", align=False, export="export-off")
    assert len(cloud.alignments) == 12
    x = np.linspace(0.0, 120.0, 7)
    moved = max(np.max(np.abs(al.true_to_reported(x) - x)) for al in cloud.alignments.values())
    print(f"largest implied move of a pass: {moved * 100:.1f} cm")
    assert moved < cloud.settings.align_apply_m
    on, off = (pq.read_table(plain / e / "profile.parquet").to_pydict() for e in ("export", "export-off"))
    assert on["chainage_m"] == off["chainage_m"] and on["n_passes"] == off["n_passes"]
    # The same segments fused (re-fused after the sweep: the same sums in another order).
    np.testing.assert_allclose(on["elevation_m"], off["elevation_m"], rtol=0, atol=1e-9 * np.std(off["elevation_m"]))
    assert _frames(plain / "export") == _frames(plain / "export-off") == {REGISTRY_FRAME}


def test_default_run_with_gnss_error_on_the_second_world(fleets, tmp_path):
    """The same target on data the estimators were not shaped on (the ivp world: its own integrator,
    logger chain, prior-drawn vehicles, slowly varying speed, logs starting mid-motion, chainage
    integrated from an odometer with a per-run scale error): with GNSS bias and 2 % odometer error,
    the default run's profile in the fleet's frame within 1.2x of that world's run with exact
    chainage, the vehicles' k/M and c/M within 3 %."""
    scenario = dataclasses.replace(SCENARIOS["road-qc-gnss"], route_length_m=120.0)
    gnss, plain = tmp_path / "ivp-gnss", tmp_path / "ivp-plain"
    ivp.generate(scenario, gnss, seed=SEED, passes=12, vehicles=12, workers=1, progress=False)
    exact = dataclasses.replace(scenario, name="road-qc", gnss_bias_sd_m=0.0, gnss_jitter_sd_m=0.0, speed_error_sd=0.0)
    ivp.generate(exact, plain, seed=SEED, passes=12, vehicles=12, workers=1, progress=False,
                 settings=ivp.WorldSettings(speed_error_sd=0.0))
    fleets.run(gnss, "fleet")
    fleets.run(plain, "fleet")
    truth = load_truth(gnss / "truth.json")
    score = score_profile(gnss / "export", truth, fit_frame=True).rel_error
    reference = score_profile(plain / "export", load_truth(plain / "truth.json")).rel_error
    ratios = score_vehicles(gnss / "export", truth)
    print(f"ivp world, default run: profile {score:.4f} with GNSS error in the fleet's frame, {reference:.4f} with "
          "exact chainage; ratio medians " + ", ".join(f"{k} {v[0] * 100:.2f} %" for k, v in ratios.items()))
    assert score <= 1.2 * reference
    assert ratios["k/M"][0] <= 0.03 and ratios["c/M"][0] <= 0.03
    assert _frames(gnss / "export") == {FLEET_FRAME}
