"""USB enumeration of Intel Movidius (Luxonis OAK) devices through ``pyusb``.

Used by :meth:`cellcal.drivers.oak.camera.OakCamera.discover` when ``depthai`` is absent or
finds nothing: it lists devices with vendor id 0x03E7 and names their boot state
from the product id. ``pyusb`` needs the native ``libusb-1.0`` library; without it
:class:`UsbBackendMissingError` says so.
"""

from __future__ import annotations

from dataclasses import dataclass

from cellcal.devices.errors import MissingDependencyError, UsbBackendMissingError

#: Intel Movidius USB vendor id (every OAK / Myriad X / RVC2 device).
MOVIDIUS_VENDOR_ID = 0x03E7
#: Product id -> boot state.
BOOT_STATES: dict[int, str] = {
    0x2485: "unbooted",
    0xF63B: "booted",
    0xF63C: "bootloader",
    0xF63D: "flash-booted",
}


@dataclass(frozen=True)
class UsbDevice:
    """One USB device found by enumeration.

    Attributes:
        vendor_id: USB vendor id.
        product_id: USB product id.
        state: Boot state named from the product id ("unknown" for other ids).
        bus: USB bus number.
        address: Device address on the bus.
        port_path: Port numbers from the root hub, dotted (e.g. ``"1.2"``), "" if unknown.
    """

    vendor_id: int
    product_id: int
    state: str
    bus: int
    address: int
    port_path: str = ""


def boot_state(product_id: int) -> str:
    """Boot state of a Movidius device from its USB product id."""
    return BOOT_STATES.get(product_id, "unknown")


def find_usb_devices(vendor_id: int = MOVIDIUS_VENDOR_ID) -> list[UsbDevice]:
    """Enumerate USB devices of one vendor (no device is opened).

    Raises:
        MissingDependencyError: If ``pyusb`` is not installed (extra ``oak``).
        UsbBackendMissingError: If libusb-1.0 is not available to pyusb.
    """
    try:
        import usb.core
    except ImportError:
        raise MissingDependencyError("pyusb", "oak") from None
    try:
        found = list(usb.core.find(find_all=True, idVendor=vendor_id) or [])
    except usb.core.NoBackendError:
        raise UsbBackendMissingError(
            "pyusb found no USB backend: install libusb-1.0 (e.g. apt-get install libusb-1.0-0)") from None
    out = []
    for dev in found:
        ports = getattr(dev, "port_numbers", None) or ()
        out.append(UsbDevice(vendor_id=int(dev.idVendor), product_id=int(dev.idProduct),
                             state=boot_state(int(dev.idProduct)), bus=int(dev.bus or 0),
                             address=int(dev.address or 0), port_path=".".join(str(p) for p in ports)))
    return out
