"""``driveby demo``: the embedded default — simulate, run through edge and cloud, summarise."""

from __future__ import annotations

import sys
from pathlib import Path

import pyarrow.parquet as pq

from shared.registry import load_site

from .evaluate import load_truth, score_profile
from .run import RunError, run
from .scenarios import SCENARIOS
from .sim import generate

DEMO_SCENARIO = "bridge-crack10-10m-rough"


def bridge_lines(export: Path, truth: dict, deck: str = "rough") -> list[str]:
    """The bridge's state from the export, beside the simulation's truth (the demo may read it)."""
    summary, elements = export / "bridge_summary.parquet", export / "bridge_elements.parquet"
    if not summary.exists() or not elements.exists():
        return []
    rows = pq.read_table(elements).to_pylist()
    out = []
    tb = truth.get("bridge") or {}
    for s in pq.read_table(summary).to_pylist():
        mine = [r for r in rows if r["bridge_id"] == s["bridge_id"]]
        if not mine:
            out.append(f"bridge {s['bridge_id']:<13}{s['n_passes']} passes: too few for an estimate")
            continue
        weak = min(mine, key=lambda r: r["stiffness_ratio"])
        mean = sum(r["stiffness_ratio"] for r in mine) / len(mine)
        true_ratio = tb.get("stiffness_ratio") or []
        true_weak = (1 + min(range(len(true_ratio)), key=true_ratio.__getitem__)) if true_ratio else None
        truth_text = ""
        if tb.get("crack_x_m") is not None:
            truth_text = (f" (truth: crack phi={100 * tb['crack_phi']:.0f} % at {tb['crack_x_m']:.0f} m, "
                          f"element {true_weak}, ratio {min(true_ratio):.3f})")
        elif tb.get("global_loss"):
            truth_text = f" (truth: uniform ratio {1 - tb['global_loss']:.3f})"
        out.append(f"bridge {s['bridge_id']:<13}{s['n_passes']} passes: mean stiffness ratio {mean:.3f}, "
                   f"weakest element {weak['element']} at {weak['x_start_m']:.0f}–{weak['x_end_m']:.0f} m ratio "
                   f"{weak['stiffness_ratio']:.3f}{truth_text}")
        out.append(f"                     D1 {s['D1_pct']:.1f} %, D2 {s['D2_pct']:.1f} %; "
                   + ("ALARM raised" if s["damaged"] else "no alarm")
                   + (" (rough deck: damage hypotheses off)" if deck == "rough" else ""))
    return out


def demo(out: str | Path = "driveby-demo", seed: int = 0, passes: int = 20) -> int:
    out = Path(out)
    scenario = SCENARIOS[DEMO_SCENARIO]
    print(f"driveby demo: {scenario.description} ({passes} passes) → {out}/")
    try:
        generate(scenario, out / "sim", seed=seed, passes=passes)
    except OSError as e:  # e.g. --out names an existing file, or a read-only place
        print(f"driveby demo: cannot write to {out}: {e.strerror or e}", file=sys.stderr)
        return 1
    try:
        res = run(out / "sim" / "logs", out / "sim" / "site.toml", out / "export", rrd=out / "demo.rrd")
    except RunError as e:
        print(f"driveby demo: {e}", file=sys.stderr)
        return 1
    truth = load_truth(out / "sim" / "truth.json")
    score = score_profile(out / "export", truth)
    rejected = sum(res.stats.get("rejected", {}).values())
    print(f"passes processed     {res.acked}/{res.passes} in {res.seconds:.1f} s "
          f"({res.stats.get('accepted', 0)} segments accepted, {rejected} rejected)")
    print(f"road profile error   {100 * score.rel_error:.1f} % of the true profile's std "
          f"(0.5–50 m band), {100 * score.coverage:.0f} % of points inside the 95 % band")
    deck = load_site(out / "sim" / "site.toml").bridges[0].deck  # the registry's word (rough: estimated)
    for line in bridge_lines(out / "export", truth, deck):
        print(line)
    print(f"export               {out / 'export'} ({', '.join(Path(p).name for p in res.export)})")
    print(f"rerun recording      {out / 'demo.rrd'}  (view: rerun {out / 'demo.rrd'})")
    return 0
