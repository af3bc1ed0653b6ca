"""deploy/udev: the rule that lets a non-root user (group plugdev, or the person at the seat) open a Kinova arm on
USB, for the kinova_sdk backend; the robot_gateway unit's user is in that group."""
import configparser
import re

from tests.helpers import REPO

RULE = REPO / "deploy" / "udev" / "60-mfvs-kinova-arm.rules"
KINOVAS_RULE = REPO.parent / "shared" / "reference" / "kinova-sdk" / "10-kinova-arm.rules"


def _keys(rule_text: str) -> dict[str, str]:
    lines = [line for line in rule_text.splitlines() if line.strip() and not line.lstrip().startswith("#")]
    assert len(lines) == 1, lines
    return dict(re.findall(r'([A-Z]+(?:\{\w+\})?)\+?:?={1,2}"([^"]*)"', lines[0]))


def test_the_rule_gives_kinovas_usb_arm_to_plugdev_and_the_seat_not_to_everyone():
    keys = _keys(RULE.read_text())
    assert keys["SUBSYSTEM"] == "usb" and keys["ENV{DEVTYPE}"] == "usb_device"
    assert keys["ATTR{idVendor}"] == "22cd"
    if KINOVAS_RULE.is_file():  # the vendor id Kinova's own rule matches
        assert 'ATTR{idVendor}=="22cd"' in KINOVAS_RULE.read_text()
    assert keys["GROUP"] == "plugdev" and keys["TAG"] == "uaccess"
    assert int(keys["MODE"], 8) & 0o007 == 0  # no access for others
    assert int(RULE.name.split("-")[0]) < 73  # before systemd-logind's 73-seat-late.rules applies uaccess


def test_the_gateways_unit_runs_in_the_rules_group():
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.read_string((REPO / "deploy" / "systemd" / "mfvs-robot_gateway.service").read_text())
    assert "plugdev" in unit["Service"]["SupplementaryGroups"].split()
