"""Sweeps: runs sharded over devices (2 forced CPU devices in a subprocess) equal each run alone."""

import json
import os
import pathlib
import subprocess
import sys

import numpy as np


def test_runs_sharded_over_two_devices_equal_runs_alone():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", JAX_PLATFORMS="cpu")
    script = pathlib.Path(__file__).with_name("_sharded_sweep.py")
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["devices_used"] == [0, 1]
    assert "runs" in out["spec"]
    np.testing.assert_allclose(np.array(out["sharded"]), np.array(out["alone"]), rtol=2e-5, atol=1e-6)
    assert out["padded_runs"] == 4 and out["unpadded_runs"] == 3
