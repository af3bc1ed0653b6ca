"""deploy/systemd: a unit per service (and the router), each restarting on failure with its run directory and the
lab's environment file, and every one accepted by `systemd-analyze verify` once its paths point at this checkout."""
import configparser
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from services.stack.launcher import KNOWN_SERVICES
from services.paths import DEPLOY, REPO

UNITS = DEPLOY / "systemd"


def _units() -> dict[str, Path]:
    return {path.stem.removeprefix("mfvs-"): path for path in sorted(UNITS.glob("mfvs-*.service"))}


def _rendered(path: Path, out: Path) -> Path:
    """The unit as installed from this checkout (the templates say /opt/mfvs)."""
    text = path.read_text().replace("/opt/mfvs/.venv/bin/python", sys.executable).replace("/opt/mfvs", str(REPO))
    target = out / path.name
    target.write_text(text)
    return target


def test_a_unit_for_every_service_and_the_router():
    assert set(_units()) == {*KNOWN_SERVICES, "router"}


def test_each_unit_restarts_on_failure_with_its_environment_and_run_directory():
    for name, path in _units().items():
        unit = configparser.ConfigParser(strict=False, interpolation=None)
        unit.read_string(path.read_text())
        service = unit["Service"]
        assert service["Restart"] == "on-failure", name
        assert service["EnvironmentFile"] == "-/etc/mfvs/mfvs.env", name
        assert unit["Install"]["WantedBy"] == "multi-user.target", name
        module = "services.cli router" if name == "router" else f"services.{name} "
        assert module in service["ExecStart"], name
        if name != "router":
            assert service["RuntimeDirectory"] == "mfvs" and "MFVS_RUN_DIR=/run/mfvs" in path.read_text(), name
            assert "--connect ${MFVS_ROUTER}" in service["ExecStart"], name
            assert f"$MFVS_{name.upper()}_ARGS" in service["ExecStart"], name
            assert f"MFVS_{name.upper()}_ARGS=" in (UNITS / "mfvs.env").read_text(), name


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="no systemd-analyze on this machine")
def test_systemd_accepts_every_unit(tmp_path):
    rendered = [str(_rendered(path, tmp_path)) for path in _units().values()]
    out = subprocess.run(["systemd-analyze", "verify", "--man=no", *rendered], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    # and it does read them: a unit with a broken line fails
    broken = tmp_path / "mfvs-broken.service"
    broken.write_text(Path(rendered[0]).read_text().replace("Restart=on-failure", "Restart=sometimes")
                      .replace(sys.executable, "/nonexistent/python"))
    assert subprocess.run(["systemd-analyze", "verify", "--man=no", str(broken)], capture_output=True,
                          timeout=60).returncode != 0
