"""``driveby demo``: the embedded default — simulate, run through edge and cloud, summarise."""

from __future__ import annotations

import sys
from pathlib import Path

from .evaluate import load_truth, score_profile
from .run import RunError, run
from .scenarios import SCENARIOS
from .sim import generate

DEMO_SCENARIO = "bridge-crack10-10m-rough"


def demo(out: str | Path = "driveby-demo", seed: int = 0, passes: int = 20) -> int:
    out = Path(out)
    scenario = SCENARIOS[DEMO_SCENARIO]
    print(f"driveby demo: {scenario.description} ({passes} passes) → {out}/")
    generate(scenario, out / "sim", seed=seed, passes=passes)
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
    print(f"export               {out / 'export'} ({', '.join(Path(p).name for p in res.export)})")
    print(f"rerun recording      {out / 'demo.rrd'}  (view: rerun {out / 'demo.rrd'})")
    return 0
