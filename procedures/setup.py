"""What every procedure needs before its first step: the rig, the scenario, the simulated bench
when the rig is a simulated one, and drivers whose comms log goes to the run being recorded."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lab.core.comms import CommsRecord
from lab.core.config import Rig, load_rig
from lab.core.scenario import Scenario, load_scenario


class CommsRelay:
    """A comms sink that forwards to whatever recorder is current: drivers are opened before the
    run's recorder exists (and again on resume), the bytes must still land in the run's log."""

    def __init__(self) -> None:
        self.target: Any = None

    def __call__(self, record: CommsRecord) -> None:
        if self.target is not None:
            self.target(record)


@dataclass
class Bench:
    rig: Rig
    scenario: Scenario
    sim: Any = None                # sim_devices.bench.SimBench when simulated, else None
    devices: Any = None            # drivers.devices.Devices
    relay: CommsRelay = field(default_factory=CommsRelay)
    moved: set[str] = field(default_factory=set)   # names of devices commanded to move this run

    @property
    def simulated(self) -> bool:
        return self.sim is not None

    def stop_moved(self) -> list[str]:
        """Stop every device that moved (each independently); returns what was done."""
        out = []
        if self.devices is None:
            return out
        for name in sorted(self.moved):
            dev = self.devices[name]
            if getattr(dev, "moved", True) is False:   # never commanded to move: not ours to stop
                continue
            try:
                dev.stop()
                out.append(f"{name} stopped")
            except Exception as exc:
                out.append(f"{name} STOP FAILED ({exc})")
        return out

    def close(self) -> None:
        try:
            if self.devices is not None:
                self.devices.close()
        finally:
            if self.sim is not None:
                self.sim.stop()
                self.sim = None


MAX_SPEEDUP = 1000.0
LIFT_AT_ZERO_M = 1e-5     # the lift driver's arrival tolerance


def lift_to_zero(bench: Bench, run: Any, always: bool = False) -> None:
    """Put the lift, if the rig has one, at 0: where the rig file's Stewart base pose holds, which
    every survey that does not ask for a height (the rig calibration, a 3x3x3 BORG) assumes.  A
    lift already there is only asked where it is: a run that never needs it moves nothing.
    `always`: send it home anyway (a run that will use it starts from a commanded 0, so a resumed
    run's lift is in the state the uninterrupted run's was: the simulated carriage's error is
    drawn per move)."""
    lift = getattr(bench.devices, "lift", None)
    if lift is None or (not always and abs(lift.position()) <= LIFT_AT_ZERO_M):
        return
    bench.moved.add(lift.name)
    with run.move("lift to 0") as progress:
        lift.home(progress)


def check_speedup(speedup: float | None, rig: Rig | None = None) -> None:
    """Simulated devices may run faster than the hardware, within reason: an infinite or huge
    speed-up makes every timeout zero.  With the rig, slower only as far as its simulated devices
    can still do their work: each at least the slowest speed a rig file may give it (lab/core/config.py,
    below which a device "never finishes a run"), settling within the longest settle a rig file may
    give, and a whole travel of the turntable or the lift within the longest move the drivers
    accept (drivers.motion.MAX_MOVE_S) -- else the run would start, home, and fail (or report a
    speed of 0.000) with its directory left behind."""
    import math

    from lab.core.errors import UserError

    if speedup is not None and not (math.isfinite(speedup) and 0 < speedup <= MAX_SPEEDUP):
        raise UserError(f"--speedup must be a number in (0, {MAX_SPEEDUP:g}], got {speedup!r}")
    if rig is None or rig.sim is None:
        return
    # the command's --speedup, else the rig file's own [sim] speedup: either can be too slow
    value, name = (speedup, "--speedup") if speedup is not None else (rig.sim.speedup, f"rig {rig.source}: [sim] speedup")
    slowest = min_speedup(rig)
    if value < slowest.factor:
        raise UserError(f"{name} {value:g}: {slowest.why}; the slowest this rig's simulated devices allow is "
                        f"{slowest.factor:.3g}")


@dataclass(frozen=True)
class SlowestSpeedup:
    factor: float
    why: str          # what the device could not do below it


def min_speedup(rig: Rig) -> SlowestSpeedup:
    """The smallest speed-up at which every simulated device of `rig` can still work (see
    `check_speedup`)."""
    from drivers.motion import MAX_MOVE_S
    from lab.core.config import SIM_DEVICE_KEYS, SIM_MAXIMA

    assert rig.sim is not None
    out = SlowestSpeedup(0.0, "")
    for dev in ("turntable", "stewart", "ipjr", "lift"):
        cfg = getattr(rig.sim, dev)
        if not cfg:
            continue
        key = "speed_deg_s" if "speed_deg_s" in cfg else "speed_mm_s"
        unit = key.split("_", 1)[1].replace("_", "/")
        speed, floor = float(cfg[key]), SIM_DEVICE_KEYS[dev][key][1]
        need = [(floor / speed, f"the simulated {dev} would move slower than {floor:g} {unit} ([sim.{dev}] {key} = "
                                f"{speed:g} times the speed-up)")]
        if cfg.get("settle_s", 0.0) > 0:
            need.append((cfg["settle_s"] / SIM_MAXIMA["settle_s"], f"the simulated {dev} would settle for longer than "
                                                                   f"{SIM_MAXIMA['settle_s']:g} s"))
        travel = {"turntable": ("min_deg", "max_deg"), "lift": ("min_mm", "max_mm")}.get(dev)
        if travel is not None:
            span = abs(cfg[travel[1]] - cfg[travel[0]])
            need.append((span / (speed * MAX_MOVE_S), f"the simulated {dev}'s whole travel ({span:g} "
                                                      f"{unit.split('/')[0]}) would take longer than the "
                                                      f"{MAX_MOVE_S:g} s the drivers allow one move"))
        for factor, why in need:
            if factor > out.factor:
                out = SlowestSpeedup(factor, why)
    return out


def open_bench(rig_path: str | Path | None, scenario_path: str | Path | None, *, simulate: bool | None = None,
               speedup: float | None = None, only: list[str] | None = None, borg_n: int | None = None,
               offline: bool = False) -> Bench:
    """Load the rig and scenario; start the simulated bench if the rig has a [sim] table (or
    `simulate` says so), with the BORG of size `borg_n` on its turntable (default the rig's [sim]
    borg_n: the simulation is of the run's structure); connect drivers to the served URLs.
    `offline`: no simulator and no device claimed, the drivers opened for what they know without
    their device (nothing is sent until a request: the camera's calibration file), for reading a
    run again (`lab bench replay`) beside a bench that is in use."""
    from drivers.devices import connect

    rig = load_rig(rig_path)
    scenario = load_scenario(scenario_path)
    check_speedup(speedup, rig if (rig.sim is not None if simulate is None else simulate) else None)
    if scenario_path is None and rig.sim is not None:
        scenario = Scenario(seed=rig.sim.seed)
    # the Stewart base stands at the station that clears this BORG's turntable (docs/hardware.md)
    rig = rig.for_borg(borg_n if borg_n is not None else rig.sim.borg_n if rig.sim is not None else 3)
    bench = Bench(rig, scenario)
    if offline:
        bench.devices = connect(rig, bench.relay, only=only, claim=False)
        return bench
    use_sim = rig.sim is not None if simulate is None else simulate
    if use_sim:
        from sim_devices.bench import start_sim_bench

        bench.sim = start_sim_bench(rig, scenario, speedup=speedup, borg_n=borg_n)  # arms the scenario's device faults
        rig = bench.sim.rig
        bench.rig = rig
    try:
        bench.devices = connect(rig, bench.relay, only=only)   # claims every device first (DeviceBusy)
    except BaseException:
        bench.close()
        raise
    return bench


def check_borg_n(n: int | None) -> int | None:
    """`--n`, refused before a simulated bench is built for it."""
    from lab.core.structures.borg import MAX_N

    if n is not None and not 2 <= n <= MAX_N:
        from lab.core.errors import UserError

        raise UserError(f"--n {n}: the BORG size must be an integer from 2 to {MAX_N}")
    return n
