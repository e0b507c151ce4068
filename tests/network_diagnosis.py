"""Diagnosis of the network scenario's accuracy (a report tool, not a test; truth is read here only).

    python tests/network_diagnosis.py NET CLEAN OUT VARIANT...

``NET``: ``driveby sim network --out NET [--passes N --vehicles N] --nominal true``; ``CLEAN``: the
same seed and vehicles as ``driveby sim network-clean``. Each variant runs edge and cloud in process
(`simfleet.harness`) and scores every route (profile error in the 0.5–50 m band in the registry's
frame and in the fleet's, with the band's coverage; IRI per 100 m):

* ``clean``: the clean single-route passes (every vehicle over every route, exact chainage);
* ``matched``: the same clean passes cropped to the chainage each network pass covers (the same
  coverage as the field drives, exact chainage);
* ``truth``: the network passes cut from the drives, their chainage and speed replaced by the truth
  (what the edge's field steps cost apart from chainage);
* ``affine`` / ``shift``: the truth's chainage plus what a perfect shift-and-stretch / shift-only
  alignment of each pass would leave of the edge's chainage error;
* ``frame``: the truth's chainage plus only the shift and stretch of the edge's error (what the
  cloud's alignment is there to remove: a route worse here than under ``truth`` is misaligned);
* ``mm``: the network passes as the edge cuts them (map matching and fusion);
* ``draws``: the comparison of `tests/test_network_accuracy.py` — the mean profile error of the
  ``mm`` passes and of the ``matched`` ones over :data:`DRAWS` noise draws added alike to both, each
  draw's error and the ratio per route (a route's mean is carried by a draw whose alignment failed
  as much as by the typical one, so the draws are listed); ``draws-nominal`` is the test's reading;
* ``chainage``: per pass, the edge's chainage error against the truth: its shift, its stretch and
  what a shift and a stretch leave (rms, max; what the cloud's alignment cannot remove).

Suffixes: ``-noalign`` turns the cloud's alignment off, ``-nominal`` calibrates nominally (else fleet).
The truth substitution happens here, between the splitter and the replay: product code never sees it.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from cloud.daemon.settings import CloudSettings
from edge.trip import TripSettings, split_drives
from shared.drivelog import list_drive_logs, read_drive_log
from shared.registry import load_site
from shared.sensors import add_noise
from simfleet.evaluate import score_iri, score_profile
from simfleet.harness import run_in_process
from simfleet.network import route_truths


#: Noise draws the field and clean passes' mean error is taken over, each added on top of the
#: simulation's own 2 % noise, the same process on both sides (2 % of each pass channel's std).
DRAWS = 4
NOISE_PCT = 2.0
SCORES = ("profile_stretch_frame", "coverage_stretch_frame", "iri_median")


def network_passes(netdir: Path, settings: TripSettings = TripSettings()):
    site = load_site(netdir / "site.toml")
    paths = list_drive_logs(netdir / "logs")
    _, passes, cut = split_drives(paths, [read_drive_log(p) for p in paths], site, settings)
    return site, passes, cut


def _truth_track(truth: dict, pass_id: str):
    tr = next(p for p in truth["passes"] if p["pass_id"] == pass_id)
    return np.asarray(tr["t"]), np.asarray(tr["chainage"]), np.asarray(tr["speed"])


def with_true_chainage(passes, truth):
    """The passes with the truth's chainage and speed, and the edge's chainage errors (m)."""
    out, errs = [], []
    for p in passes:
        t, c, v = _truth_track(truth, p.meta.pass_id.rsplit("-", 2)[0])
        ct = np.interp(p.t, t, c)
        errs.append(p.chainage - ct)
        out.append(dataclasses.replace(p, chainage=ct, speed=np.interp(p.t, t, v)))
    return out, np.concatenate(errs)


def with_residual_chainage(passes, truth, model: str):
    """The passes with the truth's chainage plus the part of the edge's chainage error that a
    perfect pass alignment would leave: ``affine`` removes each pass's best shift and stretch,
    ``shift`` its mean error only, anything else nothing; ``frame`` keeps only the shift and stretch."""
    out = []
    for p in passes:
        t, c, v = _truth_track(truth, p.meta.pass_id.rsplit("-", 2)[0])
        ct = np.interp(p.t, t, c)
        e = p.chainage - ct
        A = np.stack([np.ones_like(ct), ct - ct.mean()], 1)[:, : {"affine": 2, "shift": 1, "frame": 2}.get(model, 0)]
        sol, *_ = np.linalg.lstsq(A, e, rcond=None) if A.shape[1] else (np.zeros(0),)
        r = A @ sol if model == "frame" else e - A @ sol
        # The edge's chainage within a pass is the integrated speed: the speed carries the residual.
        out.append(dataclasses.replace(p, chainage=ct + r, speed=np.interp(p.t, t, v) + np.gradient(r, p.t)))
    return out


def matched_clean(cleandir: Path, net_passes):
    """The clean pass of each network pass's vehicle and route, cropped to the chainage it covers."""
    clean = {(g.meta.vehicle_id, g.meta.route_id): g for g in map(read_drive_log, list_drive_logs(cleandir / "logs"))}
    out = []
    for k, q in enumerate(net_passes):
        c = clean[(q.meta.vehicle_id, q.meta.route_id)]
        m = (c.chainage >= np.min(q.chainage)) & (c.chainage <= np.max(q.chainage))
        out.append(dataclasses.replace(c, meta=dataclasses.replace(c.meta, pass_id=f"matched{k:03d}"),
                                       t=c.t[m] - c.t[m][0], chainage=c.chainage[m], speed=c.speed[m],
                                       channels={n: v[m] for n, v in c.channels.items()}))
    return out


def noisy(passes, rng: np.random.Generator, pct: float = NOISE_PCT):
    """The passes with ``pct`` % more noise on every channel (`shared.sensors.add_noise`)."""
    return [dataclasses.replace(p, channels={k: add_noise(v, pct, rng).astype(np.float32)
                                             for k, v in p.channels.items()}) for p in passes]


def draw_scores(field, field_site, clean, clean_site, truth: dict, out: Path, draws: int = DRAWS,
                settings: CloudSettings = CloudSettings(calibration="nominal")) -> dict[str, list[dict]]:
    """``score_routes`` of the field and of the clean passes under each of ``draws`` noise draws
    (draw ``d`` seeds both sides alike), run in process: ``{"field": [...], "clean": [...]}``."""
    runs = {"field": [], "clean": []}
    for d in range(draws):
        for name, ps, st in (("field", field, field_site), ("clean", clean, clean_site)):
            run_in_process(noisy(ps, np.random.default_rng(1000 + d)), st, out / f"{name}-draw{d}", settings)
            runs[name].append(score_routes(out / f"{name}-draw{d}", truth))
    return runs


def mean_scores(runs: list[dict]) -> dict[str, dict]:
    """Per route, the mean over draws of each of :data:`SCORES` the first draw has (a draw
    that did not score the route counts as infinite error)."""
    return {rid: {k: float(np.mean([r.get(rid, {}).get(k, np.inf) for r in runs])) for k in SCORES if k in row}
            for rid, row in runs[0].items()}


def chainage_report(passes, truth: dict) -> list[tuple[str, float, float, float, float]]:
    """Per pass: id, the chainage error's shift (m) and stretch (fraction) fitted against the
    truth's chainage, and the rms and max (m) of what they leave."""
    out = []
    for p in passes:
        t, c, _ = _truth_track(truth, p.meta.pass_id.rsplit("-", 2)[0])
        ct = np.interp(p.t, t, c)
        e = p.chainage - ct
        A = np.stack([np.ones_like(ct), ct - ct.mean()], 1)
        sol, *_ = np.linalg.lstsq(A, e, rcond=None)
        r = e - A @ sol
        out.append((p.meta.pass_id, float(sol[0]), float(sol[1]), float(np.sqrt(np.mean(r**2))), float(np.max(np.abs(r)))))
    return out


def _scored_stretch(export: Path, route_id: str, out: Path) -> Path:
    """A copy of the export's profile with only the stretch of ``route_id`` that `score_profile`
    scores (its longest run of points), so that a frame fitted to it is that stretch's own."""
    t = pq.read_table(Path(export) / "profile.parquet")
    d = t.to_pydict()
    rows = np.flatnonzero(np.asarray(d["route_id"]) == route_id)
    x = np.asarray(d["chainage_m"])[rows]
    h = float(np.median(np.diff(x))) if x.size > 1 else 1.0
    runs = np.split(np.arange(x.size), np.flatnonzero(np.diff(x) > 1.5 * h) + 1)
    keep = rows[max(runs, key=len)]
    out.mkdir(parents=True, exist_ok=True)
    pq.write_table(t.take(keep), out / "profile.parquet")
    return out


def score_routes(export: Path, truth: dict) -> dict:
    """Per route: profile error in the registry's frame, in the fleet's (one shift and stretch of
    the whole route fitted), in the scored stretch's own frame (fitted to that stretch alone:
    stretches no pass links each carry their own passes' mean GNSS error), band coverage, IRI."""
    rows = {}
    for rid, tr in route_truths(truth).items():
        row = {}
        try:
            a, b = score_profile(export, tr), score_profile(export, tr, fit_frame=True)
            row |= {"profile": a.rel_error, "profile_fleet_frame": b.rel_error, "coverage": a.coverage,
                    "coverage_fleet_frame": b.coverage, "max_passes": a.max_passes}
            with tempfile.TemporaryDirectory() as tmp:
                c = score_profile(_scored_stretch(export, rid, Path(tmp)), tr, fit_frame=True)
            row |= {"profile_stretch_frame": c.rel_error, "coverage_stretch_frame": c.coverage}
            ir = score_iri(export, tr)
            row |= {"iri_median": ir.median_rel_error, "iri_coverage": ir.coverage, "iri_segments": ir.n_segments}
        except (ValueError, KeyError) as e:
            row["note"] = str(e)
        rows[rid] = row
    return rows


def main(argv: list[str]) -> None:
    netdir, cleandir, out = Path(argv[0]), Path(argv[1]), Path(argv[2])
    truth = json.loads((netdir / "truth.json").read_text())
    results = {}
    for var in argv[3:]:
        t0 = time.time()
        settings = CloudSettings(calibration="nominal" if "nominal" in var else "fleet", align="noalign" not in var)
        if var.startswith("draws"):
            site, passes, _ = network_passes(netdir)
            runs = draw_scores(passes, site, matched_clean(cleandir, passes), load_site(cleandir / "site.toml"), truth,
                               out / var, settings=settings)
            field, clean = mean_scores(runs["field"]), mean_scores(runs["clean"])
            results[var] = {"field": field, "clean": clean}
            for rid in sorted(clean):
                f, c = field[rid].get(SCORES[0], np.nan), clean[rid].get(SCORES[0], np.nan)
                each = lambda side: " ".join(f"{r.get(rid, {}).get(SCORES[0], np.nan):.3f}" for r in runs[side])
                print(f"  {rid}: ratio {f / c:.2f}  field {f:.3f} [{each('field')}] coverage "
                      f"{field[rid].get(SCORES[1], np.nan):.2f}  clean {c:.3f} [{each('clean')}]")
            print(f"{var}: {time.time() - t0:.0f} s")
            continue
        if var.startswith("chainage"):
            site, passes, _ = network_passes(netdir)
            rows = chainage_report(passes, truth)
            _, e = with_true_chainage(passes, truth)
            print(f"chainage: |error| median {np.median(np.abs(e)):.2f} m, p95 {np.percentile(np.abs(e), 95):.2f} m")
            for pid, b, eps, rms, mx in rows:
                print(f"  {pid}: shift {b:+.2f} m, stretch {100 * eps:+.2f} %, beyond them rms {1000 * rms:.1f} mm, "
                      f"max {1000 * mx:.1f} mm")
            results[var] = {"passes": rows}
            continue
        if var.startswith("clean"):
            site = load_site(cleandir / "site.toml")
            passes = [read_drive_log(p) for p in list_drive_logs(cleandir / "logs")]
        else:
            site, passes, cut = network_passes(netdir)
            if var.startswith("matched"):
                passes = matched_clean(cleandir, passes)
            elif var.startswith(("affine", "shift", "speed", "frame")):
                passes = with_residual_chainage(passes, truth, var.split("-")[0])
            elif var.startswith("truth"):
                passes, e = with_true_chainage(passes, truth)
                print(f"  chainage error |e|: median {np.median(np.abs(e)):.3f} m, p95 {np.percentile(np.abs(e), 95):.3f} m")
        run_in_process(passes, site, out / var, settings)
        results[var] = score_routes(out / var, truth)
        print(f"{var}: {len(passes)} passes, {time.time() - t0:.0f} s")
        for rid, r in results[var].items():
            print(f"  {rid}: " + ", ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}" for k, v in r.items()))
        sys.stdout.flush()
    out.mkdir(parents=True, exist_ok=True)
    (out / "diagnosis.json").write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main(sys.argv[1:])
