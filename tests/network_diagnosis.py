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
* ``mm``: the network passes as the edge cuts them (map matching and fusion).

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
from simfleet.evaluate import score_iri, score_profile
from simfleet.harness import run_in_process
from simfleet.network import route_truths


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
    ``shift`` its mean error only, anything else nothing."""
    out = []
    for p in passes:
        t, c, v = _truth_track(truth, p.meta.pass_id.rsplit("-", 2)[0])
        ct = np.interp(p.t, t, c)
        e = p.chainage - ct
        A = np.stack([np.ones_like(ct), ct - ct.mean()], 1)[:, : {"affine": 2, "shift": 1}.get(model, 0)]
        sol, *_ = np.linalg.lstsq(A, e, rcond=None) if A.shape[1] else (np.zeros(0),)
        r = e - A @ sol
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
        if var.startswith("clean"):
            site = load_site(cleandir / "site.toml")
            passes = [read_drive_log(p) for p in list_drive_logs(cleandir / "logs")]
        else:
            site, passes, cut = network_passes(netdir)
            if var.startswith("matched"):
                passes = matched_clean(cleandir, passes)
            elif var.startswith(("affine", "shift", "speed")):
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
    (out / "diagnosis.json").write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main(sys.argv[1:])
