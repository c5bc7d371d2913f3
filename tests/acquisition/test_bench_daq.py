"""bench/daq.py runs as a script, prints one JSON line, streams without loss and keeps up with 51.2 kHz in real time
(no overrun). The figures are checked for sanity only: how fast is the bench's to measure, against its baselines."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
BENCH = REPO / "bench" / "daq.py"
HOSTS = ("transport_ceiling", "decode_only", "driver")
FIGURES = ("samples", "wall_s", "samples_per_s", "values_per_s", "payload_mb_s", "host_cpu_s", "host_cpu_pct",
           "host_cpu_s_per_m_values", "cpu_pct_at_51200hz", "device_cpu_s", "device_cpu_pct")

pytestmark = pytest.mark.timeout(120)


def test_bench_daq_prints_one_json_line_without_loss():
    out = subprocess.run([sys.executable, str(BENCH), "--samples", "100000", "--realtime-s", "1", "--repeats", "1"],
                         capture_output=True, text=True, timeout=110, cwd=REPO)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.strip().splitlines()
    assert len(lines) == 1, out.stdout
    result = json.loads(lines[0])
    assert result["bench"] == "daq" and result["channels"] == 8 and result["rate_hz"] == 51200
    assert result["cpu_count"] >= 1

    sustained = result["sustained"]
    for host in HOSTS:
        r = sustained[host]
        for key in FIGURES:
            assert r[key] is not None and r[key] >= 0, (host, key)
        for key in ("samples_per_s", "values_per_s", "payload_mb_s", "wall_s"):
            assert r[key] > 0, (host, key)
        # The span starts once START is done; the packets that arrived before it are not counted.
        assert 50_000 <= r["samples"] <= 130_000, (host, r["samples"])
        assert r["values_per_s"] == pytest.approx(8 * r["samples_per_s"], rel=1e-3)
        assert r["limited_by"] in ("device", "host", "cpus", "pty_handoff"), (host, r["limited_by"])
    for host in ("decode_only", "driver"):
        r = sustained[host]
        assert r["gaps"] == 0 and r["lost_samples"] == 0 and not r["overrun"], host
        assert not any(r["link_errors"].values()), (host, r["link_errors"])
    assert sustained["no_loss"] is True
    # The ring buffer holds what the device sent: within half an LSB (+ float32 rounding) of the sine truth.
    assert sustained["driver"]["max_error_lsb"] <= 0.51
    for key in ("rate_ratio_vs_decode_only", "rate_ratio_vs_transport_ceiling", "cpu_per_value_ratio_vs_decode_only"):
        assert sustained[key] > 0, key
    assert sustained["realtime_margin_x"] == pytest.approx(sustained["driver"]["samples_per_s"] / 51_200, abs=0.01)

    realtime = result["realtime"]
    assert realtime["seconds"] == 1.0 and realtime["no_loss"] is True
    for host in ("decode_only", "driver"):
        r = realtime[host]
        assert not r["overrun"] and r["gaps"] == 0, (host, r)
        assert r["samples"] >= 50_000
        assert r["samples_per_s"] > 0 and 0 < r["host_cpu_pct"] <= 100 * result["cpus_available"], (host, r)
        assert r["limited_by"] == "device_clock"


def test_bench_daq_rejects_bad_options():
    out = subprocess.run([sys.executable, str(BENCH), "--block", "9999"], capture_output=True, text=True, timeout=60,
                         cwd=REPO)
    assert out.returncode == 2 and "--block" in out.stderr and not out.stdout
