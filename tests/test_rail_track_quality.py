"""EN 13848 D1 longitudinal level (shared.track_quality) and its export table."""

from __future__ import annotations

import numpy as np
import pyarrow.parquet as pq
import pytest

from cloud.road.mean_profile import ProfileSnapshot
from cloud.export import track_quality_table, vehicles_table, write_export
from shared.track import RailIrregularity
from shared.track_quality import d1_longitudinal_level, isolated_defects, segment_quality

DX = 0.05


def test_band_passes_3_to_25_m_and_rejects_the_rest():
    x = np.arange(0.0, 600.0, DX)
    for wavelength, gain in ((10.0, (0.97, 1.02)), (5.0, (0.93, 1.02)), (1.0, (0.0, 0.02)), (120.0, (0.0, 0.05))):
        d1 = d1_longitudinal_level(1e-3 * np.sin(2 * np.pi * x / wavelength), DX)
        ok = np.isfinite(d1)
        amplitude = np.sqrt(2) * d1[ok].std() / 1e-3
        assert gain[0] <= amplitude <= gain[1], (wavelength, amplitude)


def test_random_track_sd_matches_the_spectrum_in_band():
    """German low-disturbance irregularity: the D1 sd per 200 m scatters about the spectrum's
    band-limited sd (measured: mean ratio 0.95 over 2 km, the filter's skirts)."""
    irr = RailIrregularity(seed=3)
    x = np.arange(0.0, 2000.0, DX)
    segs = segment_quality(x, d1_longitudinal_level(irr.elevation(x), DX))
    assert [s.start_m for s in segs] == list(np.arange(0.0, 2000.0, 200.0))
    lam = 2 * np.pi / irr.omega
    band = (lam >= 3.0) & (lam <= 25.0)
    expected_mm = 1e3 * np.sqrt((irr.amplitude[band] ** 2).sum() / 2)
    sds = np.array([s.sd_d1_mm for s in segs])
    assert np.all(np.isfinite(sds))
    assert 0.85 < sds.mean() / expected_mm < 1.05
    assert all(s.max_abs_d1_mm > 2 * s.sd_d1_mm for s in segs)


def test_gaps_and_defects():
    x = np.arange(0.0, 400.0, DX)
    z = 0.5e-3 * np.sin(2 * np.pi * x / 12.0)
    dip = (x >= 298.5) & (x <= 301.5)  # a 3 m long, 6 mm deep dip (e.g. a wet spot)
    z[dip] -= 6e-3 * 0.5 * (1 - np.cos(2 * np.pi * (x[dip] - 298.5) / 3.0))
    z[(x > 100) & (x < 150)] = np.nan  # a stretch no pass covered
    d1 = d1_longitudinal_level(z, DX)
    assert np.all(np.isnan(d1[(x > 100) & (x < 150)]))
    assert np.all(np.isnan(d1[(x > 75.1) & (x < 100)]))  # the filter's edge is not trusted
    defects = isolated_defects(x, d1, limit_mm=2.0)  # the sine alone stays below 0.6 mm
    assert len(defects) == 1 and abs(defects[0][0] - 300.0) < 0.5 and defects[0][1] < -3.0
    assert not isolated_defects(x, d1, limit_mm=50.0)


def test_export_tables(tmp_path):
    x = np.arange(0.0, 450.0, DX)
    z = RailIrregularity(seed=5).elevation(x)
    snap = ProfileSnapshot("L1", x, z, z - 1e-4, z + 1e-4, np.full(x.size, 3))
    table = track_quality_table({"L1": snap})
    assert table.column_names == ["route_id", "start_m", "end_m", "sd_d1_mm", "max_abs_d1_mm"]
    assert table.column("start_m").to_pylist() == [0.0, 200.0, 400.0]
    assert table.column("end_m").to_pylist()[-1] == pytest.approx(x[-1])
    rows = [{"vehicle_id": "car-0001", "param": "mv", "mean": 3.2e4, "lo95": 3.1e4, "hi95": 3.3e4, "pass_id": "run001"}]
    vt = vehicles_table(rows)
    assert vt.column_names == ["vehicle_id", "param", "mean", "lo95", "hi95", "pass_id"]
    assert vehicles_table([{k: v for k, v in rows[0].items() if k != "pass_id"}]).column_names[-1] == "hi95"
    write_export(tmp_path, {"track_quality": table, "vehicles": vt})
    assert pq.read_table(tmp_path / "track_quality.parquet").num_rows == 3
