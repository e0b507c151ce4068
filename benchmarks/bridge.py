"""Bridge benchmark: time per pass update of the live estimator, and time-to-equal-accuracy
against the thesis's MCMC (§4.4.5/§4.5.4) on the same data.

Data: ``bridge-global10`` (true loss 10 %), 30 quarter-car passes, 2 % noise, vehicles
self-calibrated by the system (edge + cloud cores in process). Accuracy = |error| of the global
(effective) stiffness ratio against the truth.

* ``bridge.pass_update``: seconds to add one pass to a 29-pass estimator and re-estimate (dynamic
  model, hypotheses, MR-IL) — median of several passes.
* ``bridge.mcmc_time_to_equal_accuracy``: the MCMC (thesis settings, 2000 iterations) runs on the
  per-pass deflections of the same passes; its running posterior mean (second half of the chain so
  far) is scored after every iteration. Ratio = MCMC time to reach our accuracy / our full
  estimate time. Two MCMC clocks: as run here (a proposal updates residuals incrementally — exact
  for the quasi-static likelihood), and as the thesis runs it (one vehicle–bridge simulation per
  pass per proposal: the time of one such simulation is measured and multiplied out). When the
  chain never reaches our accuracy the ratio is a lower bound (``"bound": "lower"``).

The reference's data are each pass's drift-controlled deflection as our estimator's per-pass MR-IL
reads it (fleet-common consensus trend, support steps and the bridge's dynamic excess modelled out —
a favour to the reference: the raw AP − consensus carries a mm step at the supports that drives the
chain's class weights far from their mean within a few hundred iterations).

Why the chain does not settle on the truth — a property of the thesis's model on these data, not a
sampler bug (the sampler matches a closed-form posterior in tests/test_bridge_reference.py). At 2 %
acceleration noise each pass's deflection carries correlated error of about half its signal (σ₃² =
1e-11 assumes 3 µm), so the passes' loads, each fitted alone at the true I, scatter by about a class
mean. The likelihood is exactly invariant along W → cW, I → cI, so the scale c is set by the priors
alone, and both pull it down: (a) each one-pass vehicle's weight absorbs its pass's error, and a
Gaussian class prior on so spread a fleet is smallest at c* = Σr/Σr² < 1 (r = W/w̄), not at 1; (b) with
σ₃² that small the end elements take the near-support errors, and the GMRF prior (eq. 4.34), being on I
in m⁴ rather than on relative changes, charges these steps τ₂/2·ΣΔI², which shrinks as c². The chain
crawls down the ridge (s_I = 0.001 m⁴ is 0.08 % of I) and its running mean keeps falling: its
2 000-iteration answer is its start (design I, class-mean weights) plus drift, within our accuracy only
in transit, so the ratio is reported as a lower bound. The measurements are in docs/results.md (Bridge).

Timings are wall-clock on a shared machine; ratios are measured in the same run. The simulated and
self-calibrated passes are not what is timed: they are kept in ``$TMPDIR/driveby-bench-bridge`` and
reused by the next run.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from cloud.bridge.estimator import BridgeEstimator, BridgeSettings, class_weight_prior
from cloud.bridge.passdata import group_segments
from cloud.reference.mcmc import mcmc_bridge_elements
from shared.fe.beam import compliance_kernel
from shared.vbi import simulate_vbi
from shared.vehicles import vehicle_from_params
from simfleet.reproduce_bridge import simulate_case, true_effective

SCENARIO = "bridge-global10"
PASSES = 30


def _case(work: Path):
    return simulate_case(SCENARIO, work, passes=PASSES, seed=0)


def run(work: Path | None = None):
    work = Path(work or Path(tempfile.gettempdir()) / "driveby-bench-bridge")
    case = _case(work)
    bridge = case.site.bridges[0]
    prior = class_weight_prior(case.site, "quarter_car")
    groups = list(group_segments(case.segments).items())
    truth = true_effective(case)

    # Time per pass update.
    est = BridgeEstimator(bridge, prior, BridgeSettings())
    for (vid, _), segs in groups[:-1]:
        est.add_segments(segs, "quarter_car", case.params[vid])
    est.estimate()  # warm (numba, caches)
    times = []
    for (vid, pid), segs in groups[-3:]:
        est.remove(vid, pid)
    for (vid, pid), segs in groups[-3:]:
        t0 = time.perf_counter()
        est.add_segments(segs, "quarter_car", case.params[vid])
        e = est.estimate()
        times.append(time.perf_counter() - t0)
    per_pass = statistics.median(times)
    t0 = time.perf_counter()
    fresh = BridgeEstimator(bridge, prior, BridgeSettings())
    for (vid, _), segs in groups:
        fresh.add_segments(segs, "quarter_car", case.params[vid])
    e = fresh.estimate()
    full = time.perf_counter() - t0
    ours_err = abs(e.posterior.effective_ratio - truth)
    yield {"name": "bridge.pass_update", "value": per_pass, "unit": "s",
           "context": {"passes": PASSES, "full_estimate_s": full, "effective": e.posterior.effective_ratio,
                       "truth": truth, "abs_error": ours_err}}

    # The thesis's MCMC on the same passes' deflections: each pass's drift-controlled deflection with
    # what is not deflection modelled out as our estimator does for its per-pass MR-IL (the fleet-common
    # consensus trend μ, the pass's support steps, the bridge's dynamic excess). Raw AP − consensus
    # carries a mm step at the supports that the thesis's model can only read as 5× the class weight.
    pd = e.pass_deflections  # what the estimator's per-pass MR-IL reads (BridgeEstimate.pass_deflections)
    defl, x = list(pd.deflection_m), pd.x_m
    entries = list(fresh.passes.values())
    ids = sorted({vid for vid, _ in pd.keys})
    vehicles = [ids.index(vid) for vid, _ in pd.keys]
    beam = fresh.setup.beam
    G = compliance_kernel(beam, np.clip(x, 0.0, beam.span_m))
    g_int = np.trapezoid(G, x, axis=0)
    I_d = bridge.I_m4
    res = mcmc_bridge_elements(defl, vehicles, G, bridge.E_pa, np.full(bridge.n_elements, I_d),
                               (prior.mean_n, prior.sd_n), n_iter=2000, seed=0)
    eff = (g_int.sum() / I_d) / (res.I ** -1.0 @ g_int)  # per kept sample
    secs = res.stats["seconds"]
    reached = None
    for k in range(len(eff)):
        m = float(np.mean(eff[k // 2 : k + 1]))
        if abs(m - truth) <= ours_err:
            reached = k
            break
    # One vehicle–bridge simulation of one pass (the thesis's cost per pass per proposal).
    p0 = entries[0].data
    system = vehicle_from_params("quarter_car", case.params[p0.vehicle_id]).system()
    flat = lambda s: np.zeros_like(np.asarray(s, dtype=float))  # noqa: E731
    t0 = time.perf_counter()
    n_sim = 3
    for _ in range(n_sim):
        simulate_vbi(system, flat, flat, -5.0, p0.speed_mps, (beam.span_m + 30.0) / p0.speed_mps, 1 / 500.0,
                     beam=beam, bridge_start_m=0.0, gamma=0.5)
    t_sim = (time.perf_counter() - t0) / n_sim
    n_pass, n_veh = len(entries), len(ids)
    thesis_per_iter = t_sim * (n_pass + bridge.n_elements * n_pass)
    final_mean = float(np.mean(eff[len(eff) // 2 :]))
    if reached is None:
        t_ours_mcmc, t_thesis, bound = secs[-1], thesis_per_iter * res.stats["n_iter"], "lower"
    else:
        t_ours_mcmc, t_thesis, bound = secs[reached], thesis_per_iter * res.stats["iterations"][reached], "measured"
    yield {"name": "bridge.mcmc_time_to_equal_accuracy", "value": t_thesis / full, "unit": "x",
           "bound": bound,
           "ratio_to": {"mcmc_incremental": t_ours_mcmc / full, "mcmc_thesis_cost": t_thesis / full},
           "context": {"our_abs_error": ours_err, "mcmc_final_effective": final_mean, "truth": truth,
                       "mcmc_abs_error": abs(final_mean - truth), "mcmc_iterations": res.stats["n_iter"],
                       "mcmc_seconds": secs[-1], "vbi_pass_s": t_sim, "passes": n_pass, "vehicles": n_veh,
                       "ours_full_estimate_s": full,
                       "acceptance_elements": float(np.mean(res.stats["elements"])),
                       "mcmc_weight_over_class_mean": float(res.weights[-1].mean() / prior.mean_n),
                       "mcmc_weight_spread_over_class_sd": float(res.weights[-1].std() / prior.sd_n)}}
