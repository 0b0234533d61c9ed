"""IPJR driver (IPJR paper §5; docs/protocols.md §4–5): one driver, two transports.

An IPJR clamps onto a telescoping strut and sets its length with a linear actuator (Firgelli L-16,
140 mm stroke) whose potentiometer gives the extension.  The same commands reach it either over
HTTP GET (its Raspberry Pi) or the serial line (its Arduino); `_HttpWire` and `_SerialWire` are the
only places that differ.

Lengths:
- extension (m) from potentiometer volts through the rig's calibration (`volts_retracted` at 0,
  `volts_extended` at full stroke, linear in between);
- strut length = attach offset + extension.  When the operator attaches the IPJR they measure the
  strut (the paper's initial M_L) and call `attach(measured_length_m)`, which fixes the offset.

`set_length(L)` is the paper's controller: measure M, move round((L − M) / d_step) steps,
re-measure, until |L − M| < tolerance (0.5 mm).  (The paper writes "d_step(L − M) steps"; the
step count is the length error divided by the step length.)  It refuses a target outside the
stroke before moving, and stops with `LengthControlError` when the error does not shrink twice in
a row (divergence: the true step is more than twice the assumed one; or the actuator is stuck)
or after `max_tries` cycles."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Protocol

from drivers.driver import Actuator, http_transport, identify_line, line_transport
from drivers.errors import Disconnected, LengthControlError, OutOfRange, ProtocolError
from drivers.motion import MotionPlan, Poll, Progress, link_drops, sent_motion, stop_quietly, wait_until_idle
from drivers.transport import HttpTransport, LineTransport, Transport
from drivers.wire import parse_fields, parse_float
from lab.core.comms import CommsSink, null_sink
from lab.core.config import IpjrConfig


@dataclass(frozen=True)
class IpjrHardware:
    stroke_mm: float
    step_mm: float
    speed_mm_s: float
    settle_s: float
    max_steps: int


@dataclass(frozen=True)
class LengthResult:
    length_m: float                         # last measured strut length
    error_m: float                          # target − measured
    tries: int                              # move-measure cycles used
    history: list[tuple[int, float]] = field(default_factory=list)   # (steps, measured length m)


class _Wire(Protocol):
    link: Transport

    def identify(self) -> str: ...
    def limits(self) -> IpjrHardware: ...
    def volts(self) -> float: ...
    def step(self, n: int) -> None: ...
    def moving(self) -> bool: ...
    def stop(self) -> None: ...
    def clear(self) -> None: ...
    def status(self) -> dict[str, Any]: ...


class _SerialWire:
    """The Arduino's line protocol (docs/protocols.md §4)."""

    def __init__(self, name: str, link: LineTransport) -> None:
        self.name, self.link = name, link

    def identify(self) -> str:
        return identify_line(self.name, self.link, "IPJR", "an IPJR")

    def limits(self) -> IpjrHardware:
        req = "LIMITS?"
        f = parse_fields(self.name, req, self.link.request(req),
                         ("stroke_mm", "step_mm", "speed_mm_s", "settle_s", "max_steps"))
        return IpjrHardware(*(parse_float(self.name, req, f[k]) for k in ("stroke_mm", "step_mm", "speed_mm_s",
                                                                           "settle_s")),
                            int(parse_float(self.name, req, f["max_steps"])))

    def volts(self) -> float:
        return parse_float(self.name, "V?", self.link.request("V?"))

    def step(self, n: int) -> None:
        self.link.request(f"STEP {n}", idempotent=False)

    def moving(self) -> bool:
        reply = self.link.request("MOVING?")
        if reply not in ("0", "1"):
            raise ProtocolError(self.name, f"reply to 'MOVING?' is {reply!r}, expected 0 or 1")
        return reply == "1"

    def stop(self) -> None:
        self.link.request("STOP", idempotent=True)

    def clear(self) -> None:
        self.link.request("CLEAR", idempotent=True)

    def status(self) -> dict[str, Any]:
        req = "STATUS?"
        f = parse_fields(self.name, req, self.link.request(req), ("state", "volts", "fault"))
        return {"state": f["state"].lower(), "volts": parse_float(self.name, req, f["volts"]), "fault": f["fault"]}


class _HttpWire:
    """The Raspberry Pi's GET API (docs/protocols.md §5)."""

    def __init__(self, name: str, link: HttpTransport) -> None:
        self.name, self.link = name, link

    def _get(self, path: str, params: dict[str, Any] | None = None, *, idempotent: bool, keys: tuple[str, ...],
             check: Any = None) -> dict:
        def valid(reply: dict) -> None:   # runs inside the retry loop: a garbled query reply is retried
            missing = [k for k in keys if k not in reply]
            if missing:
                raise ProtocolError(self.name, f"reply to GET {path} lacks {', '.join(missing)}: {reply!r}")
            if check is not None:
                check(reply)

        return self.link.get_json(path, params, idempotent=idempotent, check=valid)

    def identify(self) -> str:
        r = self._get("/id", idempotent=True, keys=("device", "model", "firmware"))
        if r["device"] != "ipjr":
            raise ProtocolError(self.name, f"GET /id says device {r['device']!r}: this is not an IPJR (check the rig URL)")
        return f"IPJR {r['model']} {r['firmware']}"

    def limits(self) -> IpjrHardware:
        def numbers(r: dict) -> None:
            for k in ("stroke_mm", "step_mm", "speed_mm_s", "settle_s", "max_steps"):
                v = r[k]
                if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                    raise ProtocolError(self.name, f"reply to GET /limits: {k} {v!r} is not a number")

        r = self._get("/limits", idempotent=True, keys=("stroke_mm", "step_mm", "speed_mm_s", "settle_s", "max_steps"),
                      check=numbers)
        return IpjrHardware(float(r["stroke_mm"]), float(r["step_mm"]), float(r["speed_mm_s"]),
                            float(r["settle_s"]), int(r["max_steps"]))

    def volts(self) -> float:
        def number(r: dict) -> None:
            v = r["volts"]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ProtocolError(self.name, f"reply to GET /volts: {v!r} is not a number")

        return float(self._get("/volts", idempotent=True, keys=("volts",), check=number)["volts"])

    def step(self, n: int) -> None:
        r = self._get("/step", {"steps": n}, idempotent=False, keys=("accepted",))
        if r["accepted"] is not True:
            raise ProtocolError(self.name, f"GET /step?steps={n} was not accepted: {r!r}")

    def moving(self) -> bool:
        def boolean(r: dict) -> None:
            if not isinstance(r["moving"], bool):
                raise ProtocolError(self.name, f"reply to GET /moving: {r['moving']!r} is not true/false")

        return bool(self._get("/moving", idempotent=True, keys=("moving",), check=boolean)["moving"])

    def stop(self) -> None:
        self._get("/stop", idempotent=True, keys=("stopped",))

    def clear(self) -> None:
        self._get("/clear", idempotent=True, keys=("cleared",))

    def status(self) -> dict[str, Any]:
        return self._get("/status", idempotent=True, keys=("state", "moving", "volts", "fault"))


class Ipjr(Actuator[IpjrHardware]):
    kind = "ipjr"
    config: IpjrConfig

    def __init__(self, config: IpjrConfig, wire: _Wire) -> None:
        super().__init__(config, wire.link)
        self.wire = wire
        self.attach_offset_m: float | None = None

    @classmethod
    def open(cls, config: IpjrConfig, sink: CommsSink = null_sink) -> Ipjr:
        if config.link.url.startswith("http://"):
            return cls(config, _HttpWire(config.name, http_transport(config, sink)))
        return cls(config, _SerialWire(config.name, line_transport(config, sink)))

    # -- device data ----------------------------------------------------------------------------
    def identify(self) -> str:
        return self.wire.identify()

    def _read_hardware(self) -> IpjrHardware:
        hw = self.wire.limits()
        if hw.speed_mm_s <= 0 or hw.step_mm <= 0 or hw.max_steps < 1:
            raise ProtocolError(self.name, f"implausible actuator data {hw}")
        return hw

    def _report(self, hw: IpjrHardware, st: dict[str, Any]) -> str:
        v = self.volts()
        return (f"{st['state']}; potentiometer {v:.3f} V = extension {self.extension_from_volts(v) * 1000:.2f} mm "
                f"of {hw.stroke_mm:g} mm; step {hw.step_mm:g} mm; fault {st['fault']}")

    def status(self) -> dict[str, Any]:
        return self.wire.status()

    def moving(self) -> bool:
        return self.wire.moving()

    def stop(self) -> None:
        self.wire.stop()

    def clear(self) -> None:
        self.wire.clear()

    # -- measurement ----------------------------------------------------------------------------
    def volts(self) -> float:
        return self.wire.volts()

    def extension_from_volts(self, volts: float) -> float:
        c = self.config
        return (volts - c.volts_retracted) / (c.volts_extended - c.volts_retracted) * c.stroke_m

    def measure_extension(self) -> float:
        """Extension (m), from the mean of `samples` potentiometer readings."""
        n = self.config.samples
        return self.extension_from_volts(sum(self.wire.volts() for _ in range(n)) / n)

    def attach(self, measured_length_m: float) -> float:
        """The operator attached the IPJR to a strut and measured it (the paper's initial M_L):
        from now on strut length = offset + extension.  Returns the offset (m)."""
        if not (math.isfinite(measured_length_m) and measured_length_m > 0):
            raise ValueError(f"{self.name}: a measured strut length must be a positive number of m, got {measured_length_m!r}")
        self.attach_offset_m = measured_length_m - self.measure_extension()
        return self.attach_offset_m

    def measure_length(self) -> float:
        return self._offset() + self.measure_extension()

    def _offset(self) -> float:
        if self.attach_offset_m is None:
            raise RuntimeError(f"{self.name}: not attached to a strut: call attach(measured_length_m) first")
        return self.attach_offset_m

    def length_limits_m(self) -> tuple[float, float]:
        off = self._offset()
        return off, off + self.config.stroke_m

    # -- motion ---------------------------------------------------------------------------------
    def step(self, n: int, progress: Progress | None = None, *, extension_m: float | None = None) -> None:
        """Move n steps and wait until the actuator has stopped.  Refused before sending if |n| is
        beyond the device's max_steps or the move would run past either end of the stroke."""
        if isinstance(n, bool) or not isinstance(n, (int, float)) or not math.isfinite(n) or int(n) != n or n == 0:
            raise ValueError(f"{self.name}: steps must be a non-zero integer, got {n!r}")
        n = int(n)
        ext = self.measure_extension() if extension_m is None else extension_m
        if not math.isfinite(ext):
            raise ValueError(f"{self.name}: extension {ext!r} is not a finite number of m")
        c = self.config
        predicted = ext + n * c.step_m
        if not -0.5 * c.step_m <= predicted <= c.stroke_m + 0.5 * c.step_m:
            raise OutOfRange(self.name, "extension after the move", predicted * 1000, (0.0, c.stroke_m * 1000), "mm",
                             f"{n} steps from {ext * 1000:.3f} mm")
        hw = self.hardware()
        if abs(n) > hw.max_steps:
            raise OutOfRange(self.name, "step count", n, (-hw.max_steps, hw.max_steps), "steps", "device max_steps")
        plan = MotionPlan.of(f"{n} steps", abs(n) * hw.step_mm, hw.speed_mm_s, hw.settle_s, c.link.margin_s, self.name)
        sent_motion(self, lambda: self.wire.step(n), self.wire.stop)

        def poll() -> Poll:
            return Poll(self.wire.moving(), 0.5, "actuator still moving")

        wait_until_idle(self.name, plan, poll, self.wire.stop, progress)

    def set_length(self, length_m: float, progress: Progress | None = None) -> LengthResult:
        """The IPJR paper's length controller.  Requires `attach()` first."""
        c = self.config
        lo, hi = self.length_limits_m()
        if not (math.isfinite(length_m) and lo <= length_m <= hi):
            raise OutOfRange(self.name, "strut length", length_m, (lo, hi), "m",
                             f"the actuator's {c.stroke_m * 1000:g} mm stroke from where it was attached")
        history: list[tuple[int, float]] = []
        measured = self.measure_length()
        strikes = 0
        moves: list[float] = []
        drops0 = drops = link_drops(self.link)
        cut_short = 0          # consecutive moves during which the link dropped
        for attempt in range(1, c.max_tries + 1):
            err = length_m - measured
            if abs(err) < c.tolerance_m:
                return LengthResult(measured, err, attempt - 1, history)
            n = int(round(err / c.step_m)) or (1 if err > 0 else -1)
            ext = measured - self._offset()
            try:
                self.step(n, extension_m=ext)
            except OutOfRange as exc:  # the controller itself would drive past an end: it is diverging
                raise self._fail(f"controller asked for a move past the stroke end ({exc.message}); "
                                 f"error history {self._mm(length_m, history)}", history) from None
            if progress is not None:
                progress(min(1.0, attempt / c.max_tries))
            new = self.measure_length()
            history.append((n, new))
            now = link_drops(self.link)
            cut_short = cut_short + 1 if now > drops else 0
            drops = now
            if cut_short >= 2:   # the link keeps dropping mid-move (the actuator stops each time)
                stopped = stop_quietly(self.name, self.wire.stop)
                raise Disconnected(self.name, f"link to {self.link.url} lost during {cut_short} moves in a row; "
                                              f"length control gave up at error {self._mm(length_m, history)}; {stopped}")
            moves.append(abs(new - measured) / (abs(n) * c.step_m))   # fraction of the commanded move
            strikes = strikes + 1 if abs(length_m - new) >= abs(err) else 0
            if strikes >= 2:   # twice in a row no closer: stop before it gets worse
                if max(moves[-2:]) < 0.25:
                    raise self._fail(f"actuator did not move: {history[-1][0]} steps commanded, "
                                     f"{(new - measured) * 1000:+.3f} mm measured (stuck?); error "
                                     f"{self._mm(length_m, history)}", history)
                raise self._fail(f"length controller diverging: error {self._mm(length_m, history)} "
                                 f"(the true step is probably more than twice step_m = {c.step_m * 1000:.3f} mm)",
                                 history)
            measured = new
        err = length_m - measured
        if abs(err) < c.tolerance_m:
            return LengthResult(measured, err, c.max_tries, history)
        lost = link_drops(self.link) - drops0
        raise self._fail(f"length {length_m:.5f} m not reached within {c.tolerance_m * 1000:g} mm after "
                         f"{c.max_tries} tries; error {self._mm(length_m, history)}"
                         + (f"; the link to {self.link.url} was lost {lost} times meanwhile" if lost else ""), history)

    @staticmethod
    def _mm(target: float, history: list[tuple[int, float]]) -> str:
        return " -> ".join(f"{(target - m) * 1000:+.2f}" for _, m in history) + " mm"

    def _fail(self, message: str, history: list[tuple[int, float]]) -> LengthControlError:
        return LengthControlError(self.name, f"{message}; {stop_quietly(self.name, self.wire.stop)}", history)


__all__ = ["Ipjr", "IpjrHardware", "LengthResult"]
