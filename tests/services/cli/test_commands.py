"""The installed `mfvs` console script."""
import io
import json
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from services.runtime.transport import ZenohConfig, open_session
from services.model.arm import load_arm
from tests.helpers import signal_a_thread_not_the_main

ARM = load_arm("j2s7s300")


def mfvs_executable() -> str:
    beside_python = Path(sys.executable).parent / "mfvs"
    found = str(beside_python) if beside_python.exists() else shutil.which("mfvs")
    assert found, "the mfvs console script is not installed (run the install command in README.md)"
    return found


def run(*args, timeout=60):
    return subprocess.run([mfvs_executable(), *args], capture_output=True, text=True, timeout=timeout)


def test_help_lists_commands():
    out = run("--help")
    assert out.returncode == 0
    assert "router" in out.stdout and "model" in out.stdout


def test_no_command_prints_help_and_fails():
    out = run()
    assert out.returncode == 2 and "usage: mfvs" in out.stdout


def test_unknown_command_is_refused():
    out = run("fly")
    assert out.returncode == 2 and "invalid choice" in out.stderr and "did you mean" not in out.stderr


def test_a_mistyped_command_or_choice_gets_the_closest_one():
    out = run("servoo")
    assert out.returncode == 2 and "did you mean 'servo'?" in out.stderr
    out = run("task", "strat")
    assert out.returncode == 2 and "did you mean 'start'?" in out.stderr
    out = run("experiment", "tabel3")
    assert out.returncode == 2 and "did you mean 'table3'?" in out.stderr


def test_a_router_on_a_busy_port_says_so_without_a_traceback():
    first = subprocess.Popen([mfvs_executable(), "router", "--port", "0"], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    try:
        port = json.loads(first.stdout.readline())["router"].rsplit(":", 1)[1]
        out = run("router", "--port", port)
        assert out.returncode == 1 and "Traceback" not in out.stderr
        assert f"cannot listen on 127.0.0.1:{port}" in out.stderr and "in use" in out.stderr
    finally:
        first.kill()
        first.wait(timeout=10)


def test_model_info_and_urdf():
    info = json.loads(run("model", "info").stdout)
    assert info["home_physical_deg"] == ARM.home_deg.tolist()
    assert [j["limits_physical_deg"] for j in info["joints"]][1] == [47.0, 313.0]
    urdf = run("model", "urdf").stdout
    assert urdf.strip() == ARM.urdf().strip()
    six = json.loads(run("model", "info", "--arm", "j2n6s300", "--json").stdout)
    # the data sheets' numbers (JACO thesis appendix F): K-75+ on joints 1-3, K-58 on 4-6
    assert [(j["peak_torque_nm"], j["nominal_torque_nm"], j["max_speed_dps"]) for j in six["joints"]] == \
        [(30.5, 12.0, 36.0)] * 3 + [(6.8, 3.6, 48.0)] * 3
    assert [j["no_load_speed_dps"] for j in six["joints"]] == [73.2] * 3 + [121.8] * 3


def test_router_command_serves_and_stops_on_sigterm():
    proc = subprocess.Popen([mfvs_executable(), "router", "--port", "0"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        endpoint = json.loads(line)["router"]
        assert endpoint.startswith("tcp/127.0.0.1:")
        a = open_session(ZenohConfig(connect=[endpoint]))
        b = open_session(ZenohConfig(connect=[endpoint]))
        got = []
        b.declare_subscriber("mfvs/cli/test", lambda s: got.append(s.payload.to_bytes()))
        time.sleep(0.3)
        a.put("mfvs/cli/test", b"x")
        deadline = time.monotonic() + 5
        while not got and time.monotonic() < deadline:
            time.sleep(0.02)
        a.close()
        b.close()
        assert got == [b"x"]
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()


def test_the_router_stops_on_a_sigterm_that_one_of_zenohs_threads_received():
    proc = subprocess.Popen([mfvs_executable(), "router", "--port", "0"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        json.loads(proc.stdout.readline())  # listening: zenoh's threads run
        thread = signal_a_thread_not_the_main(proc.pid, signal.SIGTERM)
        assert proc.wait(timeout=5) == 0, f"SIGTERM on thread {thread!r} left the router running"
    finally:
        if proc.poll() is None:
            proc.kill()


def test_a_config_files_endpoints_win_and_a_conflicting_port_is_an_error(tmp_path):
    """`mfvs router --config` listens where the file says (it listened on the default 7447); a --port that
    conflicts is refused; a client's --zenoh-config endpoints win over the default and a conflicting --connect is
    refused, so no service silently joins whatever router runs on 7447."""
    import pytest

    from services.runtime.config import ConfigError
    from services.runtime.transport import free_loopback_port, to_zenoh_config

    port = free_loopback_port()
    router_file = tmp_path / "router.json5"
    router_file.write_text(json.dumps({"mode": "router", "listen": {"endpoints": [f"tcp/127.0.0.1:{port}"]}}))
    conflict = run("router", "--config", str(router_file), "--port", str(port + 1), timeout=30)
    assert conflict.returncode == 2 and "conflicts" in conflict.stderr
    proc = subprocess.Popen([mfvs_executable(), "router", "--config", str(router_file)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        assert json.loads(proc.stdout.readline())["router"] == f"tcp/127.0.0.1:{port}"
        client_file = tmp_path / "client.json5"
        client_file.write_text(json.dumps({"mode": "client", "connect": {"endpoints": [f"tcp/127.0.0.1:{port}"]}}))
        session = open_session(ZenohConfig(config_file=str(client_file)))  # the default --connect gives way
        assert session.info.routers_zid()
        session.close()
        with pytest.raises(ConfigError, match="conflict"):
            to_zenoh_config(ZenohConfig(connect=["tcp/127.0.0.1:1"], config_file=str(client_file)))
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=10)


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_experiments_send_their_iterations_to_the_command_only_where_a_progress_line_shows_them(monkeypatch):
    from types import SimpleNamespace

    from services.cli import commands as cli

    scenario = SimpleNamespace(convergence=SimpleNamespace(rms=2.5e-5, max_iterations=100))
    record = SimpleNamespace(iteration=3, error_norm=1e-2, points=[(0.0, 0.0)] * 4, keypoints=None)
    # not a terminal (a pipe, a log file, CI), or --json: the runs send nothing an iteration
    assert cli._experiment_progress("table3", quiet=False).on_iteration is None
    terminal = _Terminal()
    monkeypatch.setattr(sys, "stderr", terminal)
    assert cli._experiment_progress("table3", quiet=True).on_iteration is None
    on_iteration = cli._experiment_progress("table3", quiet=False).on_iteration
    assert on_iteration is not None
    on_iteration("p-joint", scenario, record)
    assert "table3 p-joint: iteration     3" in terminal.getvalue()
