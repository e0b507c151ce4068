"""simfleet.screenshots without a browser: frame comparison, the viewer's URL, one line on failure."""

from __future__ import annotations

import struct
import subprocess
import sys
import zlib

import pytest

from simfleet.screenshots import frame_change, main, viewer_url


def png(rows: list[bytes]) -> bytes:
    """A greyscale PNG of the given pixel rows (filter byte 0 each), encoded by hand."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    head = struct.pack(">IIBBBBB", len(rows[0]), len(rows), 8, 0, 0, 0, 0)
    raw = b"".join(b"\0" + r for r in rows)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", head) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")


def test_frame_change_is_the_share_of_changed_pixels():
    a = png([bytes(700)] * 70)
    assert frame_change(a, a) == 0.0
    b = png([bytes(700)] * 69 + [b"\xff" * 700])  # one row of 70 changed
    assert frame_change(a, b) == pytest.approx(1 / 70, rel=0.05)
    assert frame_change(a, png([bytes(10)] * 5)) == 1.0  # another size


def test_viewer_url_opens_the_proxy():
    url = viewer_url(9090, 9876)
    assert url.startswith("http://127.0.0.1:9090/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A9876%2Fproxy")


def test_a_missing_recording_is_one_line_and_exit_1(tmp_path, capsys):
    assert main([str(tmp_path / "nope.rrd"), "--out", str(tmp_path / "img")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("screenshots: ") and "no such recording" in err[0]
    done = subprocess.run([sys.executable, "-m", "simfleet.screenshots", str(tmp_path / "x.rrd"), "--size", "big"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 1 and len(done.stderr.strip().splitlines()) == 1


def test_shots_name_their_clicks():
    from simfleet.screenshots import ScreenshotError, Shot, parse_shot

    assert parse_shot("demo-view") == Shot("demo-view")
    assert parse_shot("tab@156,901;10,20") == Shot("tab", ((156, 901), (10, 20)))
    for bad in ("tab@x,y", "@1,2", "a/b"):
        with pytest.raises(ScreenshotError):
            parse_shot(bad)
