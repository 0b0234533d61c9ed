"""Simulated IPJR (IPJR paper §5): the actuator truth, and its two front ends, the Arduino's serial
line protocol (docs/protocols.md §4) and the Raspberry Pi's HTTP GET API (§5).

The truth: a Firgelli L-16-like actuator, 140 mm stroke, with the rod's extension as the state.
- The potentiometer reads `volts_retracted_true + (volts_extended_true − volts_retracted_true) ·
  extension / stroke` plus Gaussian noise, through a 10-bit ADC on a 5 V reference.  The true end
  voltages differ from the rig's calibration by `calibration_sigma_v` (seeded), so the host's
  volts→length conversion has a small real error, as after any bench calibration.
- `STEP n` moves `n · step_m · step_scale` plus N(0, move_sigma) (end switches clip at the
  stroke); `step_scale` ~ 1 + N(0, step_scale_sigma) per actuator.  A scale above 2 makes the
  paper's controller diverge (tests set it through `IpjrActuator.step_scale`).
- The strut: when the (simulated) operator attaches the IPJR to a strut of true length L0,
  `attach(L0)` ties strut length = L0 + (extension − extension at attach).

Known limitations: no load-dependent speed, no backlash or collar slip, the strut is perfectly
stiff; the ADC has no non-linearity."""

from __future__ import annotations

import threading

import numpy as np

from sim_devices.http_server import Reply, json_reply
from sim_devices.controller import Controller
from sim_devices.line_server import E_BUSY, E_FAULT, E_RANGE, E_SYNTAX, Refuse, integer, nargs
from sim_devices.motion import Axis

MODEL, FIRMWARE = "LAB-IPJR", "1.0"
ADC_BITS, VREF_V = 10, 5.0


class IpjrActuator:
    def __init__(self, name: str, *, stroke_m: float, step_m: float, axis: Axis, volts_retracted: float,
                 volts_extended: float, volts_noise_v: float, step_scale: float, move_sigma_m: float,
                 rng: np.random.Generator) -> None:
        self.name = name
        self.stroke_m = stroke_m
        self.step_m = step_m
        self.axis = axis
        self.volts_retracted = volts_retracted
        self.volts_extended = volts_extended
        self.volts_noise_v = volts_noise_v
        self.step_scale = step_scale
        self.move_sigma_m = move_sigma_m
        self.max_steps = 2 ** ADC_BITS - 1
        self.fault = "none"
        self._rng = rng
        self._lock = threading.Lock()
        self._attach: tuple[float, float] | None = None   # (strut length, extension) at attach

    def reseed(self, seed: object) -> None:
        """Restart the noise stream (potentiometer noise, move scatter), e.g. from [seed, stream,
        step, k]: a procedure step re-run after an interruption then draws what it drew the first
        time, so a resumed truss run equals the uninterrupted one."""
        with self._lock:
            self._rng = np.random.default_rng(seed)  # type: ignore[arg-type]

    def set_extension(self, extension_m: float) -> None:
        """Put the rod where it is (resume of a simulated run: the actuator of a real bench is
        still where the interrupted run left it; a new simulated bench starts elsewhere)."""
        if not 0.0 <= float(extension_m) <= self.stroke_m:
            raise ValueError(f"{self.name}: extension {extension_m} m outside the {self.stroke_m} m stroke")
        self.axis.set_position(float(extension_m))

    # -- truth ------------------------------------------------------------------------------------
    def extension_m(self) -> float:
        return float(self.axis.position())

    def attach(self, strut_length_m: float) -> None:
        """The IPJR was clamped onto a strut whose true length is `strut_length_m` right now."""
        self._attach = (float(strut_length_m), self.extension_m())

    def detach(self) -> None:
        self._attach = None

    def strut_length_m(self) -> float:
        if self._attach is None:
            raise RuntimeError(f"{self.name}: not attached to a strut (call attach first)")
        length0, ext0 = self._attach
        return length0 + self.extension_m() - ext0

    # -- what the electronics see -----------------------------------------------------------------
    def volts(self) -> float:
        with self._lock:
            noise = self._rng.normal(0.0, self.volts_noise_v) if self.volts_noise_v > 0 else 0.0
        v = self.volts_retracted + (self.volts_extended - self.volts_retracted) * self.extension_m() / self.stroke_m
        counts = int(np.clip(round((v + noise) / VREF_V * self.max_steps), 0, self.max_steps))
        return counts * VREF_V / self.max_steps

    def moving(self) -> bool:
        return self.axis.moving()

    def start_steps(self, n: int, stuck: bool = False) -> None:
        if self.fault != "none":
            raise Refuse(E_FAULT, f"fault {self.fault} latched: clear it after finding the cause")
        if abs(n) > self.max_steps:
            raise Refuse(E_RANGE, f"steps {n} outside [-{self.max_steps}, {self.max_steps}]")
        if n == 0:
            raise Refuse(E_SYNTAX, "steps must be a non-zero integer")
        if self.axis.moving():
            raise Refuse(E_BUSY, "busy: the actuator is moving (stop it first)")
        with self._lock:
            err = self._rng.normal(0.0, self.move_sigma_m) if self.move_sigma_m > 0 else 0.0
        target = float(np.clip(self.extension_m() + n * self.step_m * self.step_scale + err, 0.0, self.stroke_m))
        self.axis.start(target, stuck=stuck)

    def stop(self) -> None:
        self.axis.stop()

    def clear(self) -> None:
        self.fault = "none"

    def limits(self) -> dict[str, float]:
        return {"stroke_mm": round(self.stroke_m * 1000, 6), "step_mm": round(self.step_m * 1000, 6),
                "speed_mm_s": round(self.axis.speed * 1000, 6), "settle_s": round(self.axis.settle_s, 6),
                "max_steps": self.max_steps, "vref_volts": VREF_V}

    def state(self) -> str:
        return "fault" if self.fault != "none" else ("moving" if self.moving() else "idle")


class IpjrSerialSim(Controller):
    """The Arduino front end."""

    motion_verbs = frozenset({"STEP"})

    def __init__(self, actuator: IpjrActuator) -> None:
        super().__init__(actuator.name, actuator, f"IPJR {MODEL} {FIRMWARE}", {
            "LIMITS?": self._limits, "V?": self._v, "STEP": self._step, "MOVING?": self._moving,
            "STATUS?": self._status})
        self.act = actuator

    @property
    def fault(self) -> str:   # type: ignore[override]
        """The actuator's: the serial and HTTP front ends share one latch."""
        return self.act.fault

    @fault.setter
    def fault(self, value: str) -> None:
        self.act.fault = value

    def _limits(self, args: list[str]) -> str:
        nargs(args, 0, "LIMITS?")
        lim = self.act.limits()
        return (f"stroke_mm={lim['stroke_mm']:.3f} step_mm={lim['step_mm']:.3f} speed_mm_s={lim['speed_mm_s']:.3f} "
                f"settle_s={lim['settle_s']:.3f} max_steps={int(lim['max_steps'])} vref_v={lim['vref_volts']:.3f}")

    def _v(self, args: list[str]) -> str:
        nargs(args, 0, "V?")
        return f"{self.act.volts():.3f}"

    def _step(self, args: list[str]) -> str:
        nargs(args, 1, "STEP <n>")
        self.act.start_steps(integer(args[0], "steps"), stuck=self.take_stuck())
        return ""

    def _moving(self, args: list[str]) -> str:
        nargs(args, 0, "MOVING?")
        return "1" if self.act.moving() else "0"

    def _status(self, args: list[str]) -> str:
        nargs(args, 0, "STATUS?")
        return f"state={self.act.state().upper()} volts={self.act.volts():.3f} fault={self.act.fault}"


def ipjr_routes(act: IpjrActuator):
    """The Raspberry Pi front end: GET path -> handler (docs/protocols.md §5)."""

    def no_args(query: dict[str, str], path: str) -> None:
        if query:
            raise Refuse(E_SYNTAX, f"{path} takes no parameters, got {sorted(query)}")

    def ident(q: dict[str, str], stuck: bool) -> Reply:
        no_args(q, "/id")
        return json_reply({"device": "ipjr", "model": MODEL, "firmware": FIRMWARE, "name": act.name})

    def limits(q: dict[str, str], stuck: bool) -> Reply:
        no_args(q, "/limits")
        lim = act.limits()
        lim["max_steps"] = int(lim["max_steps"])
        return json_reply(lim)

    def volts(q: dict[str, str], stuck: bool) -> Reply:
        no_args(q, "/volts")
        return json_reply({"volts": round(act.volts(), 3)})

    def step(q: dict[str, str], stuck: bool) -> Reply:
        if set(q) != {"steps"}:
            raise Refuse(E_SYNTAX, f"/step needs exactly one parameter, steps=N; got {sorted(q)}")
        n = integer(q["steps"], "steps")
        act.start_steps(n, stuck=stuck)
        return json_reply({"accepted": True, "steps": n})

    def moving(q: dict[str, str], stuck: bool) -> Reply:
        no_args(q, "/moving")
        return json_reply({"moving": act.moving()})

    def stop(q: dict[str, str], stuck: bool) -> Reply:
        no_args(q, "/stop")
        act.stop()
        return json_reply({"stopped": True, "moving": False})

    def status(q: dict[str, str], stuck: bool) -> Reply:
        no_args(q, "/status")
        return json_reply({"state": act.state(), "moving": act.moving(), "volts": round(act.volts(), 3),
                           "fault": act.fault})

    def clear(q: dict[str, str], stuck: bool) -> Reply:
        no_args(q, "/clear")
        act.clear()
        return json_reply({"cleared": True})

    return {"/id": ident, "/limits": limits, "/volts": volts, "/step": step, "/moving": moving, "/stop": stop,
            "/status": status, "/clear": clear}
