"""``mfvs bench rs485`` (bench/rs485.py): the actuators' cycle and the exchange's latency, on the host's bus period."""
import json
import subprocess
import sys

from tests.helpers import REPO


def test_the_benchmark_paces_its_exchanges_on_the_period_asked_and_says_how_many_fit_in_it():
    out = subprocess.run([sys.executable, "-m", "bench.rs485", "--json", "--seconds", "1", "--period", "5"],
                         cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    assert result["host_period_ms"] == 5.0 and 0.0 <= result["exchanges_within_period"] <= 1.0
    assert 100 <= result["exchange_ms"]["n"] <= 201  # 200 slots in 1 s; a late wake-up skips its slots
    refused = subprocess.run([sys.executable, "-m", "bench.rs485", "--period", "4"], cwd=REPO, capture_output=True,
                             text=True, timeout=60)
    assert refused.returncode == 2 and "does not divide the DSP's 10 ms tick" in refused.stderr
