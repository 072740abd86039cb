"""A pyusb backend that answers like Kinect USB devices, for tests of the real pyusb code path.

The device model (state, a log of every control transfer, fault switches) is separate from the
``IBackend`` that pyusb calls, so tests can assert on exactly what the driver sent.
"""

from __future__ import annotations

import array
import errno
import struct
import types

import usb.backend
import usb.core


class KinectMotorModel:
    """Emulates 045e:02b0: accelerometer, tilt motor and LED."""

    def __init__(
        self,
        counts=(0, 819, 0),
        tilt_half_deg=0,
        status=0,
        product=0x02B0,
        bcd=0x010B,
        serial="A00366911234567A",
    ) -> None:
        self.counts = list(counts)
        self.tilt_half_deg = tilt_half_deg
        self.status = status
        self.led = None
        self.log = []  # (bmRequestType, bRequest, wValue, wIndex, length)
        self.unplug_after_reads = None  # int: unplug once this many state reads succeeded
        self.stall_next = 0  # stall this many next transfers
        self.unplugged = False
        self.reads = 0
        self.product = product
        self.strings = {1: "Microsoft", 2: "Xbox NUI Motor", 3: serial}
        self.desc = types.SimpleNamespace(
            bLength=18,
            bDescriptorType=1,
            bcdUSB=0x0200,
            bDeviceClass=0,
            bDeviceSubClass=0,
            bDeviceProtocol=0,
            bMaxPacketSize0=64,
            idVendor=0x045E,
            idProduct=product,
            bcdDevice=bcd,
            iManufacturer=1,
            iProduct=2,
            iSerialNumber=3,
            bNumConfigurations=1,
            address=5,
            bus=1,
            port_number=1,
            port_numbers=(1,),
            speed=2,
        )

    def control(self, request_type, request, value, index, data):
        length = len(data) if data is not None else 0
        self.log.append((request_type, request, value, index, length))
        if self.unplugged:
            raise usb.core.USBError("No such device", errno=errno.ENODEV)
        if self.stall_next > 0:
            self.stall_next -= 1
            raise usb.core.USBError("Pipe error", errno=errno.EPIPE)
        if (request_type, request) == (0x80, 0x06) and value >> 8 == 3:  # GET_DESCRIPTOR(STRING)
            idx = value & 0xFF
            body = struct.pack("<H", 0x0409) if idx == 0 else self.strings[idx].encode("utf-16-le")
            return bytes([len(body) + 2, 3]) + body
        if (request_type, request) == (0xC0, 0x32):
            if self.unplug_after_reads is not None and self.reads >= self.unplug_after_reads:
                self.unplugged = True
                raise usb.core.USBError("No such device", errno=errno.ENODEV)
            self.reads += 1
            x, y, z = self.counts
            return bytes(2) + struct.pack(">hhhbB", x, y, z, self.tilt_half_deg, self.status)
        if (request_type, request) == (0x40, 0x31):
            self.tilt_half_deg = struct.unpack("<h", struct.pack("<H", value))[0]
            self.status = 4
            return b""
        if (request_type, request) == (0x40, 0x06):
            self.led = value
            return b""
        raise usb.core.USBError("Pipe error", errno=errno.EPIPE)


class FakeUsbBackend(usb.backend.IBackend):
    """pyusb ``IBackend`` over a list of device models."""

    def __init__(self, *devices) -> None:
        self.devices = list(devices)

    def enumerate_devices(self):
        return iter([d for d in self.devices if not d.unplugged])

    def get_device_descriptor(self, dev):
        return dev.desc

    def get_configuration_descriptor(self, dev, config):
        return types.SimpleNamespace(
            bLength=9,
            bDescriptorType=2,
            wTotalLength=18,
            bNumInterfaces=1,
            bConfigurationValue=1,
            iConfiguration=0,
            bmAttributes=0xC0,
            bMaxPower=50,
            extra_descriptors=[],
        )

    def get_interface_descriptor(self, dev, intf, alt, config):
        return types.SimpleNamespace(
            bLength=9,
            bDescriptorType=4,
            bInterfaceNumber=0,
            bAlternateSetting=0,
            bNumEndpoints=0,
            bInterfaceClass=0xFF,
            bInterfaceSubClass=0,
            bInterfaceProtocol=0,
            iInterface=0,
            extra_descriptors=[],
        )

    def open_device(self, dev):
        if dev.unplugged:
            raise usb.core.USBError("No such device", errno=errno.ENODEV)
        return dev

    def close_device(self, handle):
        pass

    def set_configuration(self, handle, value):
        pass

    def get_configuration(self, handle):
        return 1

    def claim_interface(self, handle, intf):
        pass

    def release_interface(self, handle, intf):
        pass

    def ctrl_transfer(self, handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):  # noqa: N803
        out = handle.control(bmRequestType, bRequest, wValue, wIndex, data)
        if bmRequestType & 0x80:
            data[: len(out)] = array.array("B", out)
            return len(out)
        return len(data)
