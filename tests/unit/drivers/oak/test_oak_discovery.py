"""Finding and configuring an OAK without opening it: discovery through depthai, the USB fallback with each boot
state, the errors when neither depthai nor libusb is there, the config's validation, and the registry building
an unconnected camera without importing the vendor's modules.
"""

from __future__ import annotations

import sys
from typing import Any

import pytest

dai = pytest.importorskip("depthai")
from _vendor_autospec import strict_autospec  # noqa: E402
from test_oak import DEVICE_ID  # noqa: E402

from cellcal.devices.base import BackendContext  # noqa: E402
from cellcal.devices.errors import ConfigError, MissingDependencyError  # noqa: E402
from cellcal.devices.registry import default_registry  # noqa: E402
from cellcal.drivers.oak import usb_scan  # noqa: E402
from cellcal.drivers.oak.camera import OakCamera  # noqa: E402


# ---------------------------------------------------------------- discovery
def test_discover_lists_depthai_devices(mocker: Any) -> None:
    info = dai.DeviceInfo("1.3", DEVICE_ID, dai.XLinkDeviceState.X_LINK_UNBOOTED,
                          dai.XLinkProtocol.X_LINK_USB_VSC, dai.XLinkPlatform.X_LINK_MYRIAD_X,
                          dai.XLinkError_t.X_LINK_SUCCESS)
    mocker.patch.object(dai.Device, "getAllAvailableDevices", return_value=[info])
    (dev,) = OakCamera.discover(timeout=1.0)
    assert dev.serial == DEVICE_ID and dev.model == "X_LINK_MYRIAD_X"
    assert dev.extra["state"] == "X_LINK_UNBOOTED" and dev.extra["source"] == "depthai"


def _usb_device(product_id: int, bus: int, ports: tuple[int, ...]) -> Any:
    import usb.core

    d = mock_usb = strict_autospec(usb.core.Device)
    mock_usb.idVendor, mock_usb.idProduct, mock_usb.bus, mock_usb.address = 0x03E7, product_id, bus, 7
    mock_usb.port_numbers = ports
    return d


def test_discover_falls_back_to_usb_with_boot_states(mocker: Any) -> None:
    import usb.core

    mocker.patch.object(dai.Device, "getAllAvailableDevices", return_value=[])
    find = mocker.patch.object(usb.core, "find", return_value=iter([
        _usb_device(0x2485, 1, (3,)), _usb_device(0xF63B, 2, (1, 4)), _usb_device(0xF63C, 2, (2,)),
        _usb_device(0xF63D, 3, ()), _usb_device(0x1234, 3, ())]))
    devices = OakCamera.discover(timeout=1.0)
    find.assert_called_once_with(find_all=True, idVendor=0x03E7)
    assert [d.extra["state"] for d in devices] == ["unbooted", "booted", "bootloader", "flash-booted", "unknown"]
    assert devices[1].serial == "usb 2-1.4" and devices[1].model == "USB 03e7:f63b"


def test_discover_without_any_backend_says_so(mocker: Any) -> None:
    import usb.core

    mocker.patch.dict(sys.modules, {"depthai": None})
    mocker.patch.object(usb.core, "find", side_effect=usb.core.NoBackendError("No backend available"))
    with pytest.raises(MissingDependencyError, match=r"libusb-1\.0"):
        OakCamera.discover(timeout=1.0)
    with pytest.raises(usb_scan.UsbBackendMissingError, match=r"apt-get install libusb-1\.0-0"):
        usb_scan.find_usb_devices()


def test_discover_depthai_absent_usb_works(mocker: Any) -> None:
    import usb.core

    mocker.patch.dict(sys.modules, {"depthai": None})
    mocker.patch.object(usb.core, "find", return_value=iter([_usb_device(0x2485, 1, (2,))]))
    (dev,) = OakCamera.discover(timeout=1.0)
    assert dev.extra == {"state": "unbooted", "bus": 1, "address": 7, "source": "pyusb"}


# ---------------------------------------------------------------- config
def test_config_validation() -> None:
    with pytest.raises(ConfigError, match="align_socket"):
        OakCamera.from_config({"align_socket": "CAM_Z"})
    with pytest.raises(ConfigError, match="CAM_D"):
        OakCamera.from_config({"align_socket": "CAM_D"})       # stereo cannot align there
    with pytest.raises(ConfigError, match="width"):
        OakCamera.from_config({"width": 0})
    with pytest.raises(ConfigError, match="amplitude"):
        OakCamera.from_config({"amplitude": "ir"})
    assert OakCamera.from_config({}).config.amplitude == "image"


def test_registry_builds_unconnected_without_vendor_import(mocker: Any) -> None:
    mocker.patch.dict(sys.modules, {"depthai": None, "usb": None, "usb.core": None})
    cam = default_registry().create("camera", {"backend": "oak", "device_id": DEVICE_ID},
                                    BackendContext(section="camera"))
    assert isinstance(cam, OakCamera) and not cam.connected
