"""robot_gateway's kinova_sdk backend against Kinova's own SDK, as Kinova publishes it (kinova-ros): where
``$MFVS_KINOVA_SDK`` names a user's SDK, else ``../shared/reference/kinova-sdk`` beside the project; skipped, saying
why, where neither is. Every ctypes struct (size, each field's offset and width), enum value and bound function is
compared with the headers by the system C++ compiler; the libraries export what the backend binds; without an arm, InitAPI fails with
ERROR_NO_DEVICE_FOUND and robot_gateway exits 2 with one line naming it, having found the comm layer without
LD_LIBRARY_PATH. No test here can move an arm: they skip where one is plugged in."""
import ctypes
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from protocol import kinova
from services.robot_gateway import kinova_sdk as sdk_mod
from services.robot_gateway.kinova_sdk import ArmStartError, KinovaSdk
from services.runtime.transport import free_loopback_port, loopback_endpoint
from tests.helpers import REPO

#: the project's reference copy of Kinova's SDK, beside the project (as CI lays out shared/)
REFERENCE = REPO.parent / "shared" / "reference" / "kinova-sdk"
#: Kinova's USB vendor id
KINOVA_USB_VENDOR = "22cd"


def sdk_root() -> Path:
    """Kinova's SDK to test against: $MFVS_KINOVA_SDK, else the reference copy; skip when there is neither."""
    given = os.environ.get(sdk_mod.SDK_ENV)
    if given:
        return Path(given)
    if REFERENCE.is_dir():
        return REFERENCE
    pytest.skip(f"Kinova's SDK is not here: {sdk_mod.SDK_ENV} is not set and {REFERENCE} does not exist")


def headers(library: Path) -> Path:
    """The directory of Kinova's headers near its libraries (include/ or kinova-ros's include/kinova/)."""
    for base in (library.parent, *library.parents[:3]):
        for candidate in (base / "include", base / "include" / "kinova"):
            if (candidate / "KinovaTypes.h").is_file():
                return candidate
    pytest.skip(f"Kinova's headers are not near {library} (include/KinovaTypes.h)")


@pytest.fixture(scope="module")
def usb_library() -> Path:
    return sdk_mod.locate_command_layer(str(sdk_root()), "usb")


@pytest.fixture(scope="module")
def eth_library() -> Path:
    return sdk_mod.locate_command_layer(str(sdk_root()), "ethernet")


@pytest.fixture
def no_arm_plugged_in():
    for vendor in Path("/sys/bus/usb/devices").glob("*/idVendor"):
        if vendor.read_text().strip() == KINOVA_USB_VENDOR:
            pytest.skip("a Kinova arm is plugged in: these tests expect none (they would drive it)")


# ------------------------------------------------------------------------------------------------ the headers
#: every struct the backend mirrors
STRUCTS = (sdk_mod.CartesianInfo, sdk_mod.AngularInfo, sdk_mod.FingersPosition, sdk_mod.AngularPosition,
           sdk_mod.CartesianPosition, sdk_mod.UserPosition, sdk_mod.Limitation, sdk_mod.TrajectoryPoint,
           sdk_mod.TrajectoryFIFO, sdk_mod.KinovaDevice, sdk_mod.EthernetCommConfig)
#: every enum the backend uses, as named in the header
ENUMS = (kinova.ErrorCode, kinova.POSITION_TYPE, kinova.HAND_MODE, kinova.GENERALCONTROL_TYPE, kinova.ShapeType,
         kinova.GRAVITY_TYPE)
#: the header's array sizes, by the names protocol.kinova gives them
CONSTANTS = {"COMMAND_SIZE": kinova.TORQUE_COMMAND_SIZE, "GRAVITY_PARAM_SIZE": kinova.GRAVITY_PARAM_SIZE,
             "OPTIMAL_Z_PARAM_SIZE": kinova.OPTIMAL_Z_PARAM_SIZE,
             "OPTIMAL_Z_PARAM_SIZE_7DOF": kinova.OPTIMAL_Z_PARAM_SIZE_7DOF}


def _program(header: str, prefix: str, transport: str) -> str:
    """A C++ program printing, from Kinova's header, what the backend assumes: sizes and offsets, enum values,
    and whether each bound function has the type the backend calls it with."""
    lines = ["#include <cstdio>", "#include <cstddef>", "#include <type_traits>", f'#include "{header}"',
             "int main() {"]
    for struct in STRUCTS:
        name = struct.__name__
        lines.append(f'std::printf("size {name} %zu\\n", sizeof({name}));')
        for field, _ in struct._fields_:
            lines.append(f'std::printf("offset {name}.{field} %zu\\n", offsetof({name}, {field}));')
            lines.append(f'std::printf("width {name}.{field} %zu\\n", sizeof((({name}*)0)->{field}));')
    for enum in ENUMS:
        for member in enum:
            lines.append(f'std::printf("value {member.name} %ld\\n", (long)({member.name}));')
    for name in CONSTANTS:
        lines.append(f'std::printf("value {name} %ld\\n", (long)({name}));')
    init, init_binding = sdk_mod.INIT_BINDINGS[transport]
    for name, binding in {**sdk_mod.BINDINGS, init: init_binding}.items():
        pointer = binding.cpp.replace("(", "(*)(", 1)
        lines.append(f'std::printf("type {name} %d\\n", (int)std::is_same<decltype(&{prefix}{name}), {pointer}>::value);')
    lines += ["return 0;", "}"]
    return "\n".join(lines)


def _compile_and_run(tmp_path: Path, include: Path, source: str) -> dict[str, int]:
    compiler = shutil.which("c++") or shutil.which("g++")
    if compiler is None:
        pytest.skip("no C++ compiler to read Kinova's headers (deploy/install.sh installs g++)")
    (tmp_path / "layout.cpp").write_text(source)
    exe = tmp_path / "layout"
    subprocess.run([compiler, "-std=c++11", "-w", "-I", str(include), "-o", str(exe), str(tmp_path / "layout.cpp")],
                   check=True, capture_output=True)
    out = subprocess.run([str(exe)], check=True, capture_output=True, text=True).stdout
    return {" ".join(line.split()[:2]): int(line.split()[2]) for line in out.splitlines()}


@pytest.mark.parametrize("transport", ["usb", "ethernet"])
def test_every_struct_enum_and_function_is_the_headers(transport, tmp_path, usb_library):
    include = headers(usb_library)
    header, prefix = (("Kinova.API.USBCommandLayerUbuntu.h", "") if transport == "usb"
                      else ("Kinova.API.EthCommandLayerUbuntu.h", "Ethernet_"))
    init = sdk_mod.INIT_BINDINGS[transport][0]
    facts = _compile_and_run(tmp_path, include, _program(header, prefix, transport))
    mismatched = []
    for struct in STRUCTS:
        if facts[f"size {struct.__name__}"] != ctypes.sizeof(struct):
            mismatched.append(f"sizeof {struct.__name__}: header {facts[f'size {struct.__name__}']}, "
                              f"ctypes {ctypes.sizeof(struct)}")
        for field, _ in struct._fields_:
            header_offset, ours = facts[f"offset {struct.__name__}.{field}"], getattr(struct, field).offset
            if header_offset != ours:
                mismatched.append(f"{struct.__name__}.{field} at {header_offset} in the header, {ours} in ctypes")
            header_width, ours = facts[f"width {struct.__name__}.{field}"], getattr(struct, field).size
            if header_width != ours:
                mismatched.append(f"{struct.__name__}.{field} is {header_width} bytes in the header, {ours} in ctypes")
    for enum in ENUMS:
        for member in enum:
            if facts[f"value {member.name}"] != member.value:
                mismatched.append(f"{member.name} = {facts[f'value {member.name}']} in the header, {member.value} here")
    for name, value in CONSTANTS.items():
        if facts[f"value {name}"] != value:
            mismatched.append(f"{name} = {facts[f'value {name}']} in the header, {value} here")
    for name, binding in {**sdk_mod.BINDINGS, init: sdk_mod.INIT_BINDINGS[transport][1]}.items():
        if facts[f"type {name}"] != 1:
            mismatched.append(f"{prefix}{name} is not declared as {binding.cpp} in {header}")
    assert not mismatched
    assert facts["size TrajectoryPoint"] == 120 and facts["size AngularPosition"] == 40  # as the README measured
    assert facts["size EthernetCommConfig"] == 40 and facts["size KinovaDevice"] == 60


def test_the_ctypes_argument_types_pass_what_the_declared_types_say():
    """Each binding's C++ type and its ctypes argument types say the same: T& and T* are pointers, T by value is
    the struct itself (what the compiled check above holds against the header)."""
    ctypes_by_name = {struct.__name__: struct for struct in STRUCTS} | {
        "int": ctypes.c_int, "float": ctypes.c_float, "GRAVITY_TYPE": ctypes.c_int}
    for name, binding in {**sdk_mod.BINDINGS, **dict(sdk_mod.INIT_BINDINGS.values())}.items():
        inside = re.fullmatch(r"int\((.*)\)", binding.cpp).group(1)
        params = [p.strip() for p in inside.split(",") if p.strip()]
        expected = [ctypes.POINTER(ctypes_by_name[p[:-1]]) if p[-1] in "&*" else ctypes_by_name[p] for p in params]
        assert list(binding.argtypes) == expected, name


def test_every_return_code_the_headers_define_is_named_as_they_name_it(usb_library):
    include = headers(usb_library)
    defined = {}
    for layer in ("Kinova.API.USBCommLayerUbuntu.h", "Kinova.API.USBCommandLayerUbuntu.h"):
        text = (include / layer).read_text(errors="replace")
        section = text[text.index("E R R O R   C O D E S"):text.index("E N D  O F  E R R O R")]
        defined |= {name: int(value) for name, value in re.findall(r"#define\s+(\w+)\s+(\d+)", section)}
    types = (include / "KinovaTypes.h").read_text(errors="replace")
    defined |= {name: int(value) for name, value in
                re.findall(r"This is an error code\.[^#]*#define\s+(\w+)\s+(\d+)", types)}
    assert len(defined) == len(kinova.ErrorCode)
    assert {code.name: code.value for code in kinova.ErrorCode} == defined


def test_the_libraries_export_every_function_the_backend_binds(usb_library, eth_library):
    for library, transport in ((usb_library, "usb"), (eth_library, "ethernet")):
        sdk = KinovaSdk(library, transport)  # refuses a library that lacks one
        assert sdk.init_name in ("InitAPI", "InitEthernetAPI")
    # the USB header declares InitEthernetAPI, but Kinova's USB library does not export it: Ethernet is the
    # Ethernet library's (Ethernet_InitEthernetAPI)
    assert not hasattr(ctypes.CDLL(str(usb_library)), "InitEthernetAPI")


# ------------------------------------------------------------------------------------------------ the library
def test_the_comm_layer_is_found_beside_the_command_layer(usb_library, tmp_path):
    assert sdk_mod.check_comm_layer(usb_library) == usb_library.parent / "USBCommLayerUbuntu.so"
    alone = tmp_path / "USBCommandLayerUbuntu.so"
    alone.symlink_to(usb_library)  # the command layer where its comm layer is not
    with pytest.raises(ArmStartError, match=f"comm layer is missing: .* and {tmp_path} has none"):
        sdk_mod.check_comm_layer(Path(os.path.abspath(alone)))


def test_in_a_process_started_without_the_sdk_on_its_path_init_says_how_to_fix_it(usb_library, no_arm_plugged_in):
    sdk = KinovaSdk.find(str(usb_library))
    with pytest.raises(ArmStartError) as failed:
        sdk_mod.open_arm(sdk, serial=None, arm_name="j2s7s300", n_joints=7)
    if sdk_mod.loader_finds("USBCommLayerUbuntu.so"):  # pytest itself was started with it on LD_LIBRARY_PATH
        assert "InitAPI returned 1015 (ERROR_NO_DEVICE_FOUND)" in str(failed.value)
    else:
        assert f"InitAPI returned 2002 (ERROR_LOAD_COMM_DLL): the command layer could not load " \
               f"USBCommLayerUbuntu.so by bare name" in str(failed.value)
        assert f"LD_LIBRARY_PATH={usb_library.parent}" in str(failed.value)


def run_gateway(*settings: str, connect: str, timeout: float = 60.0) -> tuple[subprocess.CompletedProcess, float]:
    """robot_gateway as a user starts it, from the project's root, without LD_LIBRARY_PATH."""
    env = {k: v for k, v in os.environ.items() if k not in ("LD_LIBRARY_PATH", sdk_mod.SDK_ENV)}
    args = [sys.executable, "-m", "services.robot_gateway", "--config", "services/robot_gateway/robot_gateway.yaml",
            "--set", "backend=kinova_sdk", "--connect", connect]
    for setting in settings:
        args += ["--set", setting]
    start = time.monotonic()
    run = subprocess.run(args, capture_output=True, text=True, timeout=timeout, cwd=REPO, env=env)
    return run, time.monotonic() - start


def as_given(library: Path) -> str:
    """The library as a user names it: relative to the project's root where it is the reference copy."""
    try:
        return os.path.relpath(library, REPO) if library.is_relative_to(REFERENCE.resolve()) else str(library)
    except ValueError:
        return str(library)


def test_without_an_arm_the_gateway_exits_2_with_one_line_naming_error_no_device_found(router, usb_library,
                                                                                       no_arm_plugged_in):
    """The issue's check: `python -m services.robot_gateway --config ... --set backend=kinova_sdk --set
    sdk_library=../shared/reference/kinova-sdk/lib/x86_64-linux-gnu/USBCommandLayerUbuntu.so` with a router
    running: one line, exit 2, within 20 s; the comm layer found without LD_LIBRARY_PATH (else: 2002)."""
    run, took = run_gateway(f"sdk_library={as_given(usb_library)}", connect=router.endpoint)
    assert run.returncode == 2, run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in run.stderr, run.stderr
    assert lines[0].startswith("robot_gateway: Kinova SDK InitAPI returned 1015 (ERROR_NO_DEVICE_FOUND): no arm "
                               "found: is it powered, plugged in, and does the udev rule give you the device?")
    assert run.stdout == "" and took < 20.0


def test_a_gateway_without_its_arm_says_so_before_it_worries_about_the_router(usb_library, no_arm_plugged_in):
    nobody = loopback_endpoint(free_loopback_port())
    run, _ = run_gateway(f"sdk_library={usb_library.parent.parent.parent}", connect=nobody)  # the SDK's folder
    assert run.returncode == 2 and len(run.stderr.strip().splitlines()) == 1, run.stderr
    assert "ERROR_NO_DEVICE_FOUND" in run.stderr and "connect" not in run.stderr


def test_over_ethernet_without_an_arm_the_device_list_stays_empty_for_the_receive_timeout(eth_library):
    """Measured: Kinova's InitEthernetAPI succeeds at once without an arm (it only opens its sockets); the device
    list then waits rx_timeout_ms for arms to answer and comes back empty. On loopback, so nothing leaves this
    computer. A local address this computer does not have fails at once: 1010 (ERROR_NOT_INITIALIZED)."""
    nobody = loopback_endpoint(free_loopback_port())
    ethernet = ["sdk_transport=ethernet", f"sdk_library={eth_library}", "sdk_ethernet.local_ip=127.0.0.1",
                "sdk_ethernet.robot_ip=127.0.0.1", f"sdk_ethernet.local_cmd_port={free_loopback_port()}",
                f"sdk_ethernet.local_broadcast_port={free_loopback_port()}", "sdk_ethernet.rx_timeout_ms=500"]
    run, took = run_gateway(*ethernet, connect=nobody)
    assert run.returncode == 2 and run.stderr.strip().splitlines() == [
        "robot_gateway: no arm found at 127.0.0.1:55000 (Ethernet): is it powered, cabled to this computer's "
        "network, and is sdk_ethernet.robot_ip its address?"], run.stderr
    assert run.stdout == ""  # the vendor's progress lines went to the log (debug), not to the user
    assert 0.5 <= took < 20.0
    run, _ = run_gateway(*ethernet, "sdk_ethernet.local_ip=192.0.2.1", connect=nobody)  # TEST-NET: not ours
    assert run.returncode == 2 and len(run.stderr.strip().splitlines()) == 1, run.stderr
    assert "InitEthernetAPI returned 1010 (ERROR_NOT_INITIALIZED): could not bind 192.0.2.1" in run.stderr
