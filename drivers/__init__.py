"""Device drivers: one module per device, over the transports of `drivers.transport`.

    from drivers import connect
    with connect(load_rig(path), recorder.comms_sink) as devices:
        devices.turntable.move_to(math.radians(90))

Wire protocols: docs/protocols.md.  Rig files and usage: docs/hardware.md."""

from drivers.devices import Devices, DeviceReport, check, connect

__all__ = ["connect", "check", "Devices", "DeviceReport"]
