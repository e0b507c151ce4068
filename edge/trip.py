"""A whole drive → single-route passes the edge processes unchanged (interfaces.md §5).

Steps, each its own module: the raw IMU's orientation (`edge.orientation`; its vertical levelled by the
gyro's turn axis and gravity taken between standstills, over ``level_window_s`` blocks), the logger's timestamps
onto the nominal grid, cut at IMU gaps (`edge.resample`), GNSS fixes matched to the network
(`edge.mapmatch`), the longitudinal accelerometer's bias once per drive from the GNSS track's
speed and the standstills (`imu_bias`), and per matched stretch a smoothed chainage and speed fusing the fixes with the
IMU's along-track acceleration (`edge.fusion`). What is left is cut into passes; a sample is kept
only if the vehicle is on one unambiguously matched route, moving in the route's direction faster
than ``min_speed_mps``, with |longitudinal acceleration| at most ``max_long_acc_mps2``, |lateral
acceleration| at most ``max_lat_acc_mps2`` (a raw IMU's, over ``lat_window_s``) and a fix within
``max_fix_gap_s``, and not within ``pad_s`` of a sample that is not.

Why braking and acceleration are cut, not corrected: the inverse's vehicle models (thesis §2.2)
are vertical — bounce and pitch driven by the profile at constant speed. Braking pitches the body
through load transfer (∝ a·h/L) with the centre-of-gravity height h unknown per vehicle, and a
correction would need a longitudinal model the fleet calibration cannot identify; the transient it
leaves in ``body_acc`` would read as road. So such stretches (and the body's settling, ``pad_s``)
are cut and counted. Passes driven against chainage are rejected, not reversed: the vehicle's
response cannot be run backwards in time, and the other carriageway is another surface, which a
registry declares as its own route.

Why turns are cut: the vertical axis is known from the data to a fraction of a degree, and that
fraction of a turn's lateral acceleration (metres per second squared for a second or two) reads as
a vertical bump of centimetres once integrated — far above a good road's millimetres, in the band
the profile is scored on; a real car also rolls in a turn, which the vertical models do not have.
So a stretch turning harder than ``max_lat_acc_mps2`` is cut like a braking one.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import NamedTuple

import numpy as np
from pyproj import CRS, Transformer

from shared.drivelog import ACC_COLUMNS, GYRO_COLUMNS, MODEL_CHANNELS, DriveLog, DriveLogMeta
from shared.registry import Site

from .fusion import FusionSettings, smooth_track
from .mapmatch import MatchSettings, Network, build_network, match
from .orientation import LoggerFrame, estimate_frame, level_vertical, vehicle_channels, window_sd
from .resample import ResampleSettings, resample

logger = logging.getLogger(__name__)

#: Reasons a stretch of a drive is not fused as road, as counted in `TripResult.cut_s`.
REASONS = ("imu_gap", "off_network", "ambiguous", "against_chainage", "gnss_gap", "slow", "long_acc", "settling",
           "too_short", "turn")


class TripError(ValueError):
    """A drive the splitter cannot use at all; the message is one line."""


@dataclass(frozen=True)
class TripSettings:
    """Thresholds of the splitter (SI units); see the module docstring."""

    min_speed_mps: float = 4.0
    max_long_acc_mps2: float = 0.4
    max_lat_acc_mps2: float = 0.4
    lat_window_s: float = 1.0
    pad_s: float = 2.0
    max_fix_gap_s: float = 10.0
    min_pass_m: float = 40.0
    heading_window_s: float = 5.0
    max_turn_rad: float = 0.2
    level_window_s: float = 1.0
    max_bridge_s: float = 2.0
    resample: ResampleSettings = field(default_factory=ResampleSettings)
    match: MatchSettings = field(default_factory=MatchSettings)
    fusion: FusionSettings = field(default_factory=FusionSettings)

    def __post_init__(self):
        for k in ("min_speed_mps", "max_long_acc_mps2", "max_lat_acc_mps2", "lat_window_s", "pad_s", "max_fix_gap_s", "min_pass_m", "heading_window_s",
                  "max_turn_rad", "level_window_s", "max_bridge_s"):
            v = getattr(self, k)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"TripSettings.{k}: must be a positive finite number, got {v!r}")


class TripResult(NamedTuple):
    """The passes cut from a drive, the seconds cut for each reason (`REASONS`), the fixes' match
    (route index, chainage per fix, in the drive's fix order) and the logger frame (None when the
    log had the vehicle's channels already)."""

    passes: list[DriveLog]
    cut_s: dict[str, float]
    fix_t: np.ndarray
    fix_route: list[str | None]
    fix_chainage: np.ndarray
    frame: LoggerFrame | None


def site_network(site: Site, settings: MatchSettings = MatchSettings()) -> Network:
    """The matching network of a site's routes that have geometry."""
    routes = {r.id: r.geometry for r in site.routes if r.geometry is not None}
    if not routes:
        raise TripError("the site registry has no route with geometry: a drive with positions cannot be matched")
    return build_network(routes, settings)


def split_drives(paths: list, logs: list[DriveLog], site: Site, settings: TripSettings = TripSettings()
                 ) -> tuple[list, list[DriveLog], dict[str, float]]:
    """Passes pass through; every drive with positions is cut into passes over the site's routes.

    Returns the source path of each resulting pass (for messages), the passes, and the seconds cut
    per reason over all drives. Raises `TripError` naming the file of a log that is neither.
    """
    out_paths, out_logs = [], []
    cut = dict.fromkeys(REASONS, 0.0)
    network = None
    for path, log in zip(paths, logs):
        if log.is_pass:
            out_paths.append(path)
            out_logs.append(log)
            continue
        if not log.has_positions:
            raise TripError(f"{path}: neither a pass (chainage, route, uniform step, the model's channels) nor a "
                            "drive with lat/lon")
        network = network if network is not None else site_network(site, settings.match)
        res = split_trip(log, network, settings, str(path))
        for k, v in res.cut_s.items():
            cut[k] += v
        logger.info("%s: %d passes; cut %s", path, len(res.passes),
                    ", ".join(f"{k} {v:.1f} s" for k, v in res.cut_s.items() if v > 0))
        out_paths += [path] * len(res.passes)
        out_logs += res.passes
    return out_paths, out_logs, cut


def split_trip(log: DriveLog, network: Network, settings: TripSettings = TripSettings(),
               name: str = "<drive log>") -> TripResult:
    """Cut the drive ``log`` (with ``lat``/``lon``) into passes over ``network``'s routes."""
    if log.lat is None:
        raise TripError(f"{name}: no lat/lon: not a drive the splitter can match")
    fs = log.meta.sample_rate_hz
    t = np.asarray(log.t, float)
    cut = dict.fromkeys(REASONS, 0.0)
    fix = np.isfinite(log.lat)
    t_fix, lat, lon = t[fix], log.lat[fix], log.lon[fix]
    acc_fix = None if log.gnss_accuracy_m is None else np.asarray(log.gnss_accuracy_m, float)[fix]
    m = match(network, lat, lon, acc_fix, settings.match)
    sd_fix = np.where(np.isfinite(acc_fix), acc_fix, settings.match.default_sigma_m) if acc_fix is not None \
        else np.full(len(t_fix), settings.match.default_sigma_m)
    sd_fix = np.maximum(sd_fix, settings.match.sigma_floor_m)

    model = log.meta.vehicle_model
    wanted = MODEL_CHANNELS[model]
    raw = log.imu is not None
    if raw:
        signals = {c: log.imu[c] for c in (*ACC_COLUMNS, *[g for g in GYRO_COLUMNS if g in log.imu])}
        if "body_pitch_rate" in wanted and GYRO_COLUMNS[0] not in log.imu:
            raise TripError(f"{name}: vehicle_model {model!r} needs body_pitch_rate: the raw IMU has no gyro")
    else:
        signals = {c: log.channels[c] for c in wanted}
    try:
        runs, lost = resample(t, signals, fs, settings.resample)
    except ValueError as e:
        raise TripError(f"{name}: column 't': {e}") from None
    cut["imu_gap"] += lost
    frame = None
    if raw:
        frame = _logger_frame(runs, t_fix, lat, lon, settings, name)
        gyro_runs = None
        if GYRO_COLUMNS[0] in runs[0].signals:
            gyro_runs = [np.column_stack([r.signals[c] for c in GYRO_COLUMNS]) for r in runs]
        frame = level_vertical(frame, [np.column_stack([r.signals[c] for c in ACC_COLUMNS]) for r in runs],
                               gyro_runs, max(2, int(round(settings.level_window_s * fs))))

    per_run = []
    for run in runs:
        if raw:
            acc = np.column_stack([run.signals[c] for c in ACC_COLUMNS])
            gyro = np.column_stack([run.signals[c] for c in GYRO_COLUMNS]) if GYRO_COLUMNS[0] in run.signals else None
            vc = vehicle_channels(frame, acc, gyro)
            channels = {"body_acc": vc.body_acc}
            if vc.pitch_rate is not None:
                channels["body_pitch_rate"] = vc.pitch_rate
            per_run.append((channels, vc.long_acc, acc @ frame.lateral))
        else:
            per_run.append((dict(run.signals), None, None))
    bias = None
    if raw:
        window = max(2, int(round(settings.level_window_s * fs)))
        rests = [rest_samples(np.column_stack([r.signals[c] for c in ACC_COLUMNS]) @ frame.up, la, window)
                 for r, (_, la, _) in zip(runs, per_run)]
        bias = imu_bias([(run.t, la, lt) for run, (_, la, lt) in zip(runs, per_run)], t_fix, lat, lon, settings, rests)
    passes: list[DriveLog] = []
    for run, (channels, long_acc, lat_raw) in zip(runs, per_run):
        lat_acc = None
        if lat_raw is not None:
            w = max(1, int(round(settings.lat_window_s * fs)))
            lat_acc = np.convolve(lat_raw, np.ones(w) / w, mode="same")  # the turn, not the vibration
            if bias is not None:
                long_acc = long_acc - bias.yaw_leak * lat_raw
        channels = {c: channels[c] for c in wanted}
        passes += _passes_of_run(run.t, channels, long_acc, t_fix, m, sd_fix, network, settings, log.meta,
                                 len(passes), cut, lat_acc, bias)
    names = network.route_ids
    return TripResult(passes, cut, t_fix, [None if r < 0 else names[r] for r in m.route], m.chainage, frame)


def _passes_of_run(t, channels, long_acc, t_fix, m, sd_fix, network, settings, meta, k0, cut,
                   lat_acc=None, bias: ImuBias | None = None) -> list[DriveLog]:
    """The passes within one IMU run (uniform ``t``); adds the seconds cut to ``cut``. ``lat_acc``:
    the vehicle's lateral acceleration (m/s², smoothed), None without a raw IMU; ``bias``: the
    drive's accelerometer bias (None: each stretch's fusion finds its own)."""
    dt = float(t[1] - t[0])
    inside = (t_fix >= t[0]) & (t_fix <= t[-1])
    fi = np.flatnonzero(inside)
    keep = np.zeros(len(t), bool)
    reason = np.full(len(t), "", dtype=object)
    chain = np.full(len(t), np.nan)
    speed = np.full(len(t), np.nan)
    route_of = np.full(len(t), -1)
    if len(fi) == 0:
        cut["gnss_gap"] += len(t) * dt
        return []
    # Every sample takes the match of its nearest fix; stretches are runs of one route, unambiguous.
    near = fi[np.clip(np.searchsorted(t_fix[fi], t), 0, len(fi) - 1)]
    prev = fi[np.clip(np.searchsorted(t_fix[fi], t) - 1, 0, len(fi) - 1)]
    near = np.where(np.abs(t_fix[prev] - t) < np.abs(t_fix[near] - t), prev, near)
    gap = np.abs(t_fix[near] - t)
    label = np.where(m.ambiguous[near], -2, m.route[near])  # −2 ambiguous, −1 off the network
    reason[label == -1] = "off_network"
    reason[label == -2] = "ambiguous"
    # Stretches: maximal runs of fixes with the same usable route.
    fix_label = np.where(m.ambiguous[fi], -2, m.route[fi])
    edges = np.flatnonzero(np.diff(fix_label)) + 1
    for a, b in zip(np.concatenate(([0], edges)), np.concatenate((edges, [len(fi)]))):
        r = int(fix_label[a])
        if r < 0 or b - a < 3:
            continue
        idx = fi[a:b]
        c_fix = m.chainage[idx]
        slope = np.polyfit(t_fix[idx] - t_fix[idx[0]], c_fix, 1)[0]
        direction = 1.0 if slope >= 0 else -1.0
        sel = (t >= t_fix[idx[0]]) & (t <= t_fix[idx[-1]])
        if sel.sum() < 2:
            continue
        # Along the direction of travel the bias keeps its sign: the vehicle's forward axis is fixed.
        track = smooth_track(t[sel], None if long_acc is None else long_acc[sel], t_fix[idx], direction * c_fix,
                             sd_fix[idx], settings.fusion, *(() if bias is None else (bias.bias_mps2, bias.bias_sd_mps2)))
        where = np.flatnonzero(sel)
        chain[where] = direction * track.s
        speed[where] = track.v
        route_of[where] = r
        ok = np.full(len(where), True)
        rs = np.full(len(where), "", dtype=object)
        tests = (
            ("against_chainage", np.full(len(where), direction < 0)),
            ("gnss_gap", gap[where] > settings.max_fix_gap_s),
            ("slow", track.v < settings.min_speed_mps),
            ("long_acc", np.abs(track.a) > settings.max_long_acc_mps2),
            ("turn", np.zeros(len(where), bool) if lat_acc is None else np.abs(lat_acc[where]) > settings.max_lat_acc_mps2),
        )
        for why, bad in tests:
            rs[ok & bad] = why
            ok &= ~bad
        keep[where] = ok
        reason[where] = np.where(ok, "", rs)
    reason[(reason == "") & ~keep] = "off_network"  # samples outside every stretch (before the first fix…)
    # The body settles after each cut: widen every cut by pad_s (counted as settling).
    pad = int(round(settings.pad_s / dt))
    bad = ~keep
    if pad and bad.any():
        widened = np.convolve(bad.astype(float), np.ones(2 * pad + 1), mode="same") > 0
        reason[widened & keep] = "settling"
        keep &= ~widened
    # Route changes inside a kept run split it.
    out = []
    runs_edges = np.flatnonzero(np.diff(np.concatenate(([0], keep.astype(int), [0]))))
    for a, b in zip(runs_edges[::2], runs_edges[1::2]):
        for a2, b2 in _same_route(route_of, a, b):
            length = abs(chain[b2 - 1] - chain[a2])
            if b2 - a2 < 2 or length < settings.min_pass_m:
                reason[a2:b2] = "too_short"
                continue
            out.append(_pass_log(meta, k0 + len(out), network.route_ids[route_of[a2]], t[a2:b2], chain[a2:b2],
                                 speed[a2:b2], {c: v[a2:b2] for c, v in channels.items()}))
    for why in REASONS:
        cut[why] += float(np.sum(reason == why)) * dt
    return out


def _same_route(route_of, a, b):
    e = np.flatnonzero(np.diff(route_of[a:b])) + 1 + a
    starts = np.concatenate(([a], e))
    ends = np.concatenate((e, [b]))
    return list(zip(starts, ends))


def _pass_log(meta: DriveLogMeta, k: int, route_id: str, t, chainage, speed, channels) -> DriveLog:
    start = datetime.fromisoformat(meta.start_time_utc) + timedelta(seconds=float(t[0]))
    stamp = start.isoformat().replace("+00:00", "Z")
    pm = DriveLogMeta(meta.format, meta.version, meta.vehicle_id, route_id, meta.vehicle_model, meta.sample_rate_hz,
                      stamp, meta.lane_offset_m, meta.nominal_params, f"{meta.pass_id}-{k + 1:02d}-{route_id}")
    # The pass keeps the drive's clock (uniform on the nominal grid), so it can be traced back.
    return DriveLog(pm, np.asarray(t, float), np.asarray(chainage, float), np.asarray(speed, float),
                    {c: np.asarray(v, np.float32) for c, v in channels.items()}, True)


def _logger_frame(runs, t_fix, lat, lon, settings: TripSettings, name: str) -> LoggerFrame:
    """The logger's orientation: the IMU's and the GNSS track's accelerations at the fixes, each
    taken by the same operator — the curvature of a local quadratic fit over ``heading_window_s``
    to positions (the fixes) and to the IMU's double integral, sampled at the fixes (the fit's
    constant and linear terms absorb the integration constants). Turning fixes are left out: while
    the vehicle turns, its frame rotates within the window and the two would not compare."""
    w = settings.heading_window_s
    a_track, yaw_rate, valid = track_acceleration(t_fix, lat, lon, w)
    f_log = np.full((len(t_fix), 3), np.nan)
    for run in runs:
        acc = np.column_stack([run.signals[c] for c in ACC_COLUMNS])
        h = float(run.t[1] - run.t[0])
        vel = np.concatenate([np.zeros((1, 3)), np.cumsum(0.5 * (acc[1:] + acc[:-1]) * h, axis=0)])
        pos = np.concatenate([np.zeros((1, 3)), np.cumsum(0.5 * (vel[1:] + vel[:-1]) * h, axis=0)])
        inside = np.flatnonzero((t_fix - w / 2 >= run.t[0]) & (t_fix + w / 2 <= run.t[-1]))
        for i in inside:
            sel = np.abs(t_fix - t_fix[i]) <= w / 2
            if sel.sum() < 6:
                continue
            tt = t_fix[sel] - t_fix[i]
            V = np.column_stack([np.ones(len(tt)), tt, tt**2])
            X = np.column_stack([np.interp(t_fix[sel], run.t, pos[:, j]) for j in range(3)])
            coef, *_ = np.linalg.lstsq(V, X - X.mean(axis=0), rcond=None)
            f_log[i] = 2.0 * coef[2]
    g = float(np.linalg.norm(np.nanmean(f_log, axis=0)))
    straight = valid & (np.abs(yaw_rate) * w < settings.max_turn_rad)
    f_vehicle = np.column_stack([a_track, np.full(len(t_fix), g)])
    try:
        return estimate_frame(f_log[straight], f_vehicle[straight])
    except ValueError as e:
        raise TripError(f"{name}: raw IMU: {e}") from None


def _track_fits(t_fix: np.ndarray, lat: np.ndarray, lon: np.ndarray, window_s: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The track's velocity and acceleration (east, north; NaN where the window holds too few
    fixes) at each fix, from a local quadratic fit of the position over ``window_s``."""
    mid = len(lat) // 2
    local = CRS.from_dict({"proj": "aeqd", "lat_0": float(lat[mid]), "lon_0": float(lon[mid]), "datum": "WGS84",
                           "units": "m"})
    x, y = Transformer.from_crs("EPSG:4326", local, always_xy=True).transform(lon, lat)
    x, y = np.asarray(x), np.asarray(y)
    vel = np.full((len(t_fix), 2), np.nan)
    acc = np.full((len(t_fix), 2), np.nan)
    lo = np.searchsorted(t_fix, t_fix - window_s / 2)
    hi = np.searchsorted(t_fix, t_fix + window_s / 2)
    for i in range(len(t_fix)):
        a, b = lo[i], hi[i]
        if b - a < 6 or t_fix[b - 1] - t_fix[a] < 0.6 * window_s:
            continue
        tt = t_fix[a:b] - t_fix[i]
        V = np.column_stack([np.ones(b - a), tt, tt**2])
        cx, *_ = np.linalg.lstsq(V, x[a:b], rcond=None)
        cy, *_ = np.linalg.lstsq(V, y[a:b], rcond=None)
        vel[i] = (cx[1], cy[1])
        acc[i] = (2.0 * cx[2], 2.0 * cy[2])
    return vel, acc, np.isfinite(vel[:, 0])


def track_acceleration(t_fix: np.ndarray, lat: np.ndarray, lon: np.ndarray, window_s: float,
                       min_speed_mps: float = 3.0, still_mps: float = 0.3
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The GNSS track's acceleration in the vehicle's axes, ``(a_long, a_lat)`` (m/s², lateral to
    the left) at each fix, from a local quadratic fit of the position over ``window_s``; its yaw
    rate (rad/s); and whether it is known: moving faster than ``min_speed_mps`` (heading defined)
    or standing (slower than ``still_mps``: zero)."""
    vel, acc_en, fitted = _track_fits(t_fix, lat, lon, window_s)
    out = np.full((len(t_fix), 2), np.nan)
    yaw = np.zeros(len(t_fix))
    valid = np.zeros(len(t_fix), bool)
    for i in np.flatnonzero(fitted):
        v, acc = vel[i], acc_en[i]
        sp = float(np.hypot(*v))
        if sp >= min_speed_mps:
            u = v / sp
            out[i] = (acc @ u, u[0] * acc[1] - u[1] * acc[0])
            yaw[i] = out[i, 1] / sp
            valid[i] = True
        elif sp < still_mps:
            out[i] = 0.0
            valid[i] = True
    return out, yaw, valid


class ImuBias(NamedTuple):
    """The along-track accelerometer's error over a drive: ``bias_mps2`` (its 1σ ``bias_sd_mps2``)
    and ``yaw_leak``, the share of the lateral acceleration that reads as longitudinal (the
    forward axis's small heading error, rad)."""

    bias_mps2: float
    bias_sd_mps2: float
    yaw_leak: float


def imu_bias(runs: list[tuple[np.ndarray, np.ndarray, np.ndarray]], t_fix: np.ndarray, lat: np.ndarray,
             lon: np.ndarray, settings: TripSettings, rests: list[np.ndarray] | None = None) -> ImuBias | None:
    """The longitudinal accelerometer's bias and yaw leak, once per drive, from the GNSS track's speed.

    ``runs``: per IMU run (time, longitudinal, lateral acceleration). Per fix, the GNSS speed and the
    IMU's integrated speed are taken by the same operator (the slope of a local quadratic fit over
    ``heading_window_s``, as the orientation takes accelerations); least squares gives each run's
    initial speed, one bias and one yaw leak for the drive. The GNSS error is bounded (metres) while
    a bias's effect grows with time, so over a whole drive the bias is known to a few mm/s², where a
    single stretch's fixes (tens of seconds) leave it to centimetres per second squared — a bend of
    decimetres in every pass's chainage. Fixes while turning are left out (the fitted speed cuts the
    corner), standing ones count as speed zero. None when too few fixes are usable.

    ``rests``: per run, the samples where the IMU itself says the vehicle stands (`edge.orientation.
    standstills`). There the speed is zero exactly, not to the GNSS fit's decimetres per second: two
    rests a minute apart pin the bias to a fraction of a mm/s² (the accelerometer's noise
    integrated between them), the GNSS speed then mainly tells the yaw leak and the runs' rests apart.
    """
    w = settings.heading_window_s
    vel, _, fitted = _track_fits(t_fix, lat, lon, w)
    _, yaw_rate, valid = track_acceleration(t_fix, lat, lon, w)
    speed = np.hypot(vel[:, 0], vel[:, 1])
    speed = np.where(speed < 0.3, 0.0, speed)  # standing: the fit's speed is noise
    usable = fitted & valid & (np.abs(yaw_rate) * w < settings.max_turn_rad)
    rows, ys, run_of = [], [], []
    still_rows, still_ys = [], []
    for r, (t, a_long, a_lat) in enumerate(runs):
        h = float(t[1] - t[0])
        P = np.empty((len(t), 3))
        vint = np.empty((len(t), 2))
        for j, a in enumerate((a_long, a_lat)):
            v = np.concatenate([[0.0], np.cumsum(0.5 * (a[1:] + a[:-1]) * h)])
            vint[:, j] = v
            P[:, j] = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * h)])
        P[:, 2] = 0.5 * (t - t[0]) ** 2
        inside = np.flatnonzero(usable & (t_fix - w / 2 >= t[0]) & (t_fix + w / 2 <= t[-1]))
        for i in inside:
            sel = np.abs(t_fix - t_fix[i]) <= w / 2
            tt = t_fix[sel] - t_fix[i]
            V = np.column_stack([np.ones(len(tt)), tt, tt**2])
            X = np.column_stack([np.interp(t_fix[sel], t, P[:, j]) for j in range(3)])
            coef, *_ = np.linalg.lstsq(V, X, rcond=None)
            rows.append((r, coef[1, 1], coef[1, 2], 2.0 * coef[2, 0]))  # run, integrated lateral, integrated time, acc
            ys.append(speed[i] - coef[1, 0])
            run_of.append(r)
        for j in ([] if rests is None else rests[r]):
            still_rows.append((r, vint[j, 1], float(t[j] - t[0]), 0.0))  # standing: no acceleration either
            still_ys.append(-vint[j, 0])
    n_runs = len(runs)
    if len(ys) < 10 * (n_runs + 2):
        return None
    # Across a short IMU gap the speed goes on: the next run starts where this one ends plus what
    # the acceleration at the gap's edges adds over it (its change within a fraction of a second of
    # steady driving: ~0.1 m/s², hence the row's 1σ).
    bridge_rows, bridge_ys, bridge_sd = [], [], []
    for r in range(n_runs - 1):
        (t0, a0, l0), (t1, a1, _) = runs[r], runs[r + 1]
        gap = float(t1[0] - t0[-1])
        if gap > settings.max_bridge_s:
            continue
        k = max(1, int(round(0.2 / float(t0[1] - t0[0]))))
        h = float(t0[1] - t0[0])
        v_end = float(np.sum(0.5 * (a0[1:] + a0[:-1]) * h))
        lat_end = float(np.sum(0.5 * (l0[1:] + l0[:-1]) * h))
        edge_acc = 0.5 * (float(np.mean(a0[-k:])) + float(np.mean(a1[:k])))
        bridge_rows.append((r, lat_end, float(t0[-1] - t0[0])))
        bridge_ys.append(v_end + edge_acc * gap)
        bridge_sd.append(0.01 + 0.1 * gap)
    # speed − ∫a_long = v0_run − δ·∫a_lat − b·(t − t_run); weak priors keep δ and b finite without turns.
    # A fix's speed errs by ~0.2 m/s (m/s; refined below); a standstill's by the accelerometer's noise
    # integrated over a minute and a creeping vehicle: centimetres per second. The priors' 1σ of 0.05
    # (rad, m/s²) is far wider than either.
    sd_v, sd_still, prior = 0.2, 0.02, 0.05
    n, m, nb = len(ys), len(still_ys), len(bridge_ys)
    A0 = np.zeros((n + m + nb + 2, n_runs + 3))
    for k, (r, sl, st, ac) in enumerate(rows + still_rows):
        A0[k, r], A0[k, n_runs], A0[k, n_runs + 1], A0[k, n_runs + 2] = 1.0, -sl, -st, ac
    # v0[r+1] − v0[r] + δ·∫a_lat + b·T = ∫a_long over run r, plus the gap's share.
    for k, (r, sl, st) in enumerate(bridge_rows):
        A0[n + m + k, r + 1], A0[n + m + k, r], A0[n + m + k, n_runs], A0[n + m + k, n_runs + 1] = 1.0, -1.0, sl, st
    A0[n + m + nb, n_runs], A0[n + m + nb + 1, n_runs + 1] = 1.0 / prior, 1.0 / prior
    y0 = np.concatenate([ys, still_ys, bridge_ys, [0.0, 0.0]])
    w_rows = np.concatenate([np.full(n, 1.0 / sd_v), np.full(m, 1.0 / sd_still), 1.0 / np.asarray(bridge_sd, float),
                             [1.0, 1.0]])
    sol, *_ = np.linalg.lstsq(A0 * w_rows[:, None], y0 * w_rows, rcond=None)
    resid = (y0 - A0 @ sol)[:n]
    # Consecutive fixes share most of their error (overlapping windows, the GNSS error's wander), so
    # they are worth fewer independent values: their variance is the residuals' own, grown by the
    # residuals' integrated correlation length, in rows. Refitted with that weight.
    var_v = float(np.mean(resid**2)) * correlation_length(resid, np.asarray(run_of))
    w_rows[:n] = 1.0 / math.sqrt(max(var_v, 1e-12))
    A = A0 * w_rows[:, None]
    sol, *_ = np.linalg.lstsq(A, y0 * w_rows, rcond=None)
    cov = np.linalg.inv(A.T @ A)
    return ImuBias(float(sol[n_runs + 1]), float(np.sqrt(cov[n_runs + 1, n_runs + 1])), float(sol[n_runs]))


def correlation_length(resid: np.ndarray, group: np.ndarray) -> float:
    """The integrated correlation length (in samples, at least 1) of the residual series ``resid``
    made of runs labelled by ``group``: 1 + 2·Σρ_k over the lags k whose autocorrelation ρ_k, pooled
    over the runs, is still positive (Geyer's initial positive sequence). The variance of a mean of
    correlated samples is the white formula's times this."""
    resid = np.asarray(resid, float)
    group = np.asarray(group)
    total = float(np.sum(resid**2))
    if total <= 0.0:
        return 1.0
    out = 1.0
    for k in range(1, len(resid)):
        same = group[k:] == group[:-k]
        if not same.any():
            break
        rho = float(np.sum(resid[k:][same] * resid[:-k][same])) / total
        if rho <= 0.0:
            break
        out += 2.0 * rho
    return max(out, 1.0)


def rest_samples(vertical: np.ndarray, long_acc: np.ndarray, window: int, still_ratio: float = 0.1,
                 max_long_mps2: float = 0.05) -> np.ndarray:
    """Per standstill of one run, a sample where the vehicle surely stands: the middle of the
    quietest ``window`` (vertical specific force ``vertical``, m/s²) among those quieter than
    ``still_ratio`` of the run's median whose mean longitudinal acceleration (``long_acc``, m/s²)
    is within ``max_long_mps2`` of zero.

    Rolling, the road shakes the body at any speed worth a pass, but at walking pace only a little:
    quiet windows also take in the pulling away and the last metres of braking, which the
    longitudinal acceleration (tenths of m/s² or more) tells apart from standing.
    """
    z = np.asarray(vertical, float)
    if len(z) < 3 * window:
        return np.zeros(0, np.int64)
    sd = window_sd(z, window)
    cl = np.concatenate([[0.0], np.cumsum(np.asarray(long_acc, float))])
    along = np.abs(cl[window:] - cl[:-window]) / window
    still = (sd < still_ratio * np.median(sd)) & (along < max_long_mps2)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], still.astype(np.int8), [0]])))
    return np.asarray([a + int(np.argmin(sd[a:b])) + window // 2 for a, b in zip(edges[::2], edges[1::2])
                       if b - a >= window // 2], np.int64)
