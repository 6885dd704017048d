"""The reference firmware (firmware/) running in simavr as the robot's microcontroller.

- `Simavr`: one ddrt-simavr process (firmware/sim/harness.c) and its control channel.
- `FirmwareMcu`: the firmware as a transport-free MCU model (its UART on the control
  channel, time moved on request), the counterpart of sim_hal.mcu_emulator.McuEmulator in
  tests/test_mcu_conformance.py.
- The `firmware-sim` backend (`open_firmware_sim_hal`): the real drivers, hal/bridge.py's
  Bridge on the harness's pseudo-terminal and hal/mpu6050.py on the emulated register file,
  with the firmware's PWM driving the simulated robot, the robot's front wheel (and drive
  wheels, with `sensors.wheel_counts_per_rev` > 0) turning the encoders the firmware counts,
  its battery at the firmware's ADC and its estop input closed (`devices.set_estop`). The
  firmware is built for the config's sensors (ENCODER_CPR, WHEEL_CPR) when they differ from
  the default build's. Chosen by `hal.backend: real`, `hal.imu.bus: sim` and
  `hal.bridge.url: simavr://` (optionally `simavr://PATH/TO/FIRMWARE.elf`, relative to the
  source tree; the default is firmware/build/ddrt_bridge.elf, built with make if needed).

Time: the plant and the AVR advance in lockstep, one plant step (1 ms) at a time: the plant
integrates the step with the duties the firmware applied, its encoder count at the step's
end becomes the A/B edges of the same step on the AVR, and the AVR's mean drive over the
step is the plant's next command. Unpaced (`ddrt sim`, tests) that is all simulated time;
paced (`ddrt run`) the daemon's tick brings both up to the wall clock, as with the Python
MCU model. With `simavr://?free-running`, a paced run instead lets the harness keep the
wall clock itself (its --paced mode): the firmware's bytes then come as it sends them, as
from a USB serial adapter, and the plant tells it where the wheel is and how fast it turns;
but the harness is then a process of its own, which a busy machine can stall: measured with
a load average of 3 to 5 on two cores, arrival gaps of up to 45 ms (any process there saw
the same), against the bridge's 50 ms staleness bound. Free-running, the battery stays at
its value at start and the estop input cannot be opened (both are lockstep-only commands).
"""

from __future__ import annotations


import itertools
import os
import select
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ddrt.config import Config
from ddrt.core.wrap import wrap_i32
from hal.base import HalInitError, HalIOError
from sim_hal import firmware_build
from sim_hal.serial_urls import protocol_simavr
from ddrt.params.mpu_parts import part_by_name
from sim_hal.emulated import EmulatedRealHal, plant_mpu, real_hal_on
from sim_hal.faults import FaultyI2cBus
from sim_hal.factory import plant_config
from sim_hal.plant import SimRobot
from sim_hal.simtime import SimTime

__all__ = ["F_CPU", "FirmwareMcu", "FirmwareSimDevices", "Report", "Simavr", "ensure_built",
           "firmware_for", "open_firmware_sim_hal"]

F_CPU = 16_000_000
DEFAULT_ELF = "ddrt_bridge.elf"
HANG_ELF = "ddrt_bridge_hang.elf"
REPLY_TIMEOUT_S = 30.0
_names = itertools.count()


def ensure_built(*targets: str) -> None:
    """make the firmware targets (default: the firmware and the harness); cheap when current.
    Raises HalInitError naming the missing Debian packages."""
    try:
        firmware_build.build(*(targets or ("all", "sim")))
    except firmware_build.BuildError as e:
        raise HalInitError(str(e)) from None


@dataclass
class Report:
    """One reply of the harness to run/out: outputs now and averaged over the step."""

    cycle: int
    inst: tuple[float, float]
    mean: tuple[float, float]
    enc_count: int
    resets: int
    tx_total: int
    cpu: str
    wheels: tuple[int, int] = (0, 0)  # the counts the drive wheels' lines show
    events: list[tuple[int, float, float]] = field(default_factory=list)
    reset_causes: list[tuple[int, int]] = field(default_factory=list)
    tx: list[tuple[int, int, bytes]] = field(default_factory=list)  # (end of 1st byte, byte cycles, bytes)


class Simavr:
    """One ddrt-simavr process: `pty` is its UART's pseudo-terminal (None with pipe=True)."""

    def __init__(self, elf: str | Path, *, pipe: bool = False, paced: bool = False,
                 driver: str = "dir2", freq: int = F_CPU) -> None:
        harness = firmware_build.artifact("ddrt-simavr")
        if not harness.exists():
            raise HalInitError(f"{harness}: the simavr harness is not built (make -C firmware sim)")
        if not Path(elf).exists():
            raise HalInitError(f"{elf}: no such firmware (make -C firmware)")
        args = [str(harness), "--driver", driver, "--freq", str(freq)]
        args += ["--pipe"] if pipe else []
        args += ["--paced"] if paced else []
        args.append(str(elf))
        self.freq = freq
        self.paced = paced
        self._stderr = tempfile.TemporaryFile()
        self._buf = b""
        self._closed = False
        self._posted = 0  # commands sent with post() whose reply is still to come
        self._pending: list[str] = []
        try:
            self.proc = subprocess.Popen(args, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                         stderr=self._stderr)
        except OSError as e:
            raise HalInitError(f"cannot start {harness}: {e}") from e
        if paced:
            _favour(self.proc.pid)
        while True:
            line = self._line()
            if line.startswith("ready "):
                break
        _, pty, _freq, _mode = line.split()
        self.pty: str | None = None if pty == "-" else pty

    # -- control channel ------------------------------------------------------------------

    def _line(self) -> str:
        deadline = time.monotonic() + REPLY_TIMEOUT_S
        fd = self.proc.stdout.fileno()
        while b"\n" not in self._buf:
            left = deadline - time.monotonic()
            ready, _, _ = select.select([fd], [], [], max(0.0, left))
            if not ready:
                raise HalIOError(f"ddrt-simavr: no reply within {REPLY_TIMEOUT_S:g} s{self._stderr_tail()}")
            chunk = os.read(fd, 1 << 16)
            if not chunk:
                raise HalIOError(f"ddrt-simavr exited (code {self.proc.poll()}){self._stderr_tail()}")
            self._buf += chunk
        line, self._buf = self._buf.split(b"\n", 1)
        return line.decode()

    def _stderr_tail(self) -> str:
        try:
            self._stderr.seek(0)
            text = self._stderr.read().decode(errors="replace").strip()
        except (OSError, ValueError):
            return ""
        return f": {text[-500:]}" if text else ""

    def command(self, line: str) -> tuple[list[str], list[str]]:
        """Send one command; return (the lines before the reply, the reply's fields)."""
        if self._closed:
            raise HalIOError("ddrt-simavr: closed")
        if self._posted:
            raise HalIOError("ddrt-simavr: a posted command is still outstanding")
        try:
            self.proc.stdin.write(line.encode() + b"\n")
            self.proc.stdin.flush()
        except (BrokenPipeError, OSError) as e:
            raise HalIOError(f"ddrt-simavr: {e}{self._stderr_tail()}") from e
        before: list[str] = []
        while True:
            reply = self._line()
            if reply.startswith("ok"):
                return before, reply.split()[1:]
            if reply.startswith("err"):
                raise HalIOError(f"ddrt-simavr: {line.split()[0]}: {reply[4:]}")
            before.append(reply)

    def post(self, line: str) -> None:
        """Send a command without waiting; its reply comes from `replies()`."""
        try:
            self.proc.stdin.write(line.encode() + b"\n")
            self.proc.stdin.flush()
        except (BrokenPipeError, OSError) as e:
            raise HalIOError(f"ddrt-simavr: {e}{self._stderr_tail()}") from e
        self._posted += 1

    def replies(self) -> list[Report]:
        """The reports of posted run/enc/out commands that have arrived (never blocks)."""
        fd = self.proc.stdout.fileno()
        while self._posted and select.select([fd], [], [], 0.0)[0]:
            chunk = os.read(fd, 1 << 16)
            if not chunk:
                raise HalIOError(f"ddrt-simavr exited (code {self.proc.poll()}){self._stderr_tail()}")
            self._buf += chunk
        out = []
        while self._posted and b"\n" in self._buf:
            line, self._buf = self._buf.split(b"\n", 1)
            text = line.decode()
            if text.startswith("ok"):
                self._posted -= 1
                out.append(self._parse(self._pending, text.split()[1:]))
                self._pending = []
            elif text.startswith("err"):
                self._posted -= 1
                raise HalIOError(f"ddrt-simavr: {text[4:]}")
            else:
                self._pending.append(text)
        return out

    def _report(self, line: str) -> Report:
        before, f = self.command(line)
        return self._parse(before, f)

    @staticmethod
    def _parse(before: list[str], f: list[str]) -> Report:
        rep = Report(cycle=int(f[0]), inst=(float(f[1]), float(f[2])), mean=(float(f[3]), float(f[4])),
                     enc_count=int(f[5]), resets=int(f[6]), tx_total=int(f[7]), cpu=f[8],
                     wheels=(int(f[9]), int(f[10])))
        for b in before:
            parts = b.split()
            if parts[0] == "ev":
                rep.events.append((int(parts[1]), float(parts[2]), float(parts[3])))
            elif parts[0] == "rst":
                rep.reset_causes.append((int(parts[1]), int(parts[2])))
            elif parts[0] == "tx":
                rep.tx.append((int(parts[1]), int(parts[2]), bytes.fromhex(parts[3])))
        return rep

    def run(self, cycle: int, enc_delta: int = 0, sync: int | None = None,
            wheels: tuple[int, int] = (0, 0), battery_mv: int | None = None) -> Report:
        """Lockstep: simulate up to `cycle`, the front encoder moving `enc_delta` counts and
        the drive wheels `wheels` evenly, the battery at `battery_mv` (None: as it was);
        first wait for `sync` host bytes in total through the pty."""
        line = f"run {cycle} {enc_delta} {'-' if sync is None else sync} {wheels[0]} {wheels[1]}"
        return self._report(line + (f" {battery_mv}" if battery_mv is not None else ""))

    def set_battery(self, volts: float) -> None:
        """The battery's voltage (before the divider) from now."""
        self.command(f"bat {max(0, round(volts * 1000))}")

    def set_estop(self, open_: bool) -> None:
        """The estop input open (True) or closed from now."""
        self.command(f"estop {1 if open_ else 0}")

    def out(self) -> Report:
        return self._report("out")

    def enc(self, count: float, rate: float, wheels: tuple[float, float, float, float] | None = None) -> Report:
        """The encoder heads for `count` (since power-on), then turns on at `rate` counts/s;
        `wheels` = (left, left rate, right, right rate) likewise; returns the outputs as
        `out` does."""
        extra = "" if wheels is None else " " + " ".join(f"{w:.3f}" for w in wheels)
        return self._report(f"enc {count:.3f} {rate:.3f}{extra}")

    def send(self, data: bytes) -> int:
        """Host bytes into the UART now; returns the cycle the last one is received."""
        _, f = self.command(f"send {bytes(data).hex()}" if data else "send")
        return int(f[0])

    def reset(self) -> int:
        _, f = self.command("reset")
        return int(f[0])

    def regs(self) -> dict[str, int]:
        _, f = self.command("regs")
        return {k: int(v) for k, v in (x.split("=") for x in f[1:])}

    def close(self) -> None:
        if self._closed:
            return
        try:  # quit; its reply is not waited for (posted commands may still be answering)
            self.proc.stdin.write(b"quit\n")
            self.proc.stdin.flush()
        except (BrokenPipeError, OSError):
            pass
        self._closed = True
        for stream in (self.proc.stdin, self.proc.stdout):  # a full pipe must not hold it up
            try:
                stream.close()
            except OSError:
                pass
        try:
            self.proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self._stderr.close()

    def __enter__(self) -> "Simavr":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class FirmwareMcu:
    """The firmware in simavr as an MCU model, without a pty: `send` host bytes, `advance`
    simulated time (moving the encoder), read `outputs` (-1..1 per H-bridge, the mean of the
    last PWM period). Times in seconds since power-on. `events` holds every change of the
    outputs as (t, left, right); `reset_causes` every reset as (t, MCUSR at boot)."""

    def __init__(self, elf: str | Path | None = None, *, hang: bool = False, driver: str = "dir2") -> None:
        self.wheels = (0, 0)
        if elf is None:
            ensure_built("hang" if hang else "all", "sim")
            elf = firmware_build.artifact(HANG_ELF if hang else DEFAULT_ELF)
        self.sim = Simavr(elf, pipe=True, driver=driver)
        self.freq = self.sim.freq
        self.sim.command("events 1")
        self.cycle = 0
        self.outputs = (0.0, 0.0)
        self.resets = 0
        self.cpu = "running"
        self.enc_count = 0
        self.events: list[tuple[float, float, float]] = []
        self.reset_causes: list[tuple[float, int]] = []

    @property
    def now(self) -> float:
        return self.cycle / self.freq

    def send(self, data: bytes) -> float:
        """Host -> MCU bytes, starting now at the line rate; returns when the last one is in."""
        return self.sim.send(data) / self.freq

    def advance(self, dt: float, counts: int = 0, wheels: tuple[int, int] = (0, 0)) -> list[tuple[float, bytes]]:
        """Run `dt` seconds, the front encoder moving `counts` and the drive wheels `wheels`
        evenly; returns the MCU's bytes as (time the byte's stop bit ended, byte) runs:
        [(t, bytes), ...]."""
        target = self.cycle + max(1, round(dt * self.freq))
        rep = self.sim.run(target, counts, wheels=wheels)
        self.wheels = rep.wheels
        self.cycle = rep.cycle
        self.outputs = rep.inst
        self.resets = rep.resets
        self.cpu = rep.cpu
        self.enc_count = rep.enc_count
        self.events += [(c / self.freq, l, r) for c, l, r in rep.events]
        self.reset_causes += [(c / self.freq, cause) for c, cause in rep.reset_causes]
        return [(end / self.freq, data) for end, _bc, data in rep.tx]

    def reset(self) -> None:
        """Pull RESET low: the MCU reboots now."""
        self.sim.reset()

    def set_battery(self, volts: float) -> None:
        self.sim.set_battery(volts)

    def set_estop(self, open_: bool) -> None:
        self.sim.set_estop(open_)

    def close(self) -> None:
        self.sim.close()


# ------------------------------------------------------------------------------ backend

class FirmwareSimDevices:
    """The simulated robot, the firmware in simavr as its microcontroller, the emulated
    MPU-6050, and the clock that drives them (`time`)."""

    def __init__(self, cfg: Config, start: tuple[float, float, float], seed: int | None = None,
                 paced: bool = False, elf: str | Path | None = None, free_running: bool = False) -> None:
        if elf is None:
            elf = firmware_for(cfg.sensors.encoder_counts_per_rev, cfg.sensors.wheel_counts_per_rev)
        else:
            ensure_built("sim")
        self.wheel_counts = cfg.sensors.wheel_counts_per_rev > 0
        self.robot = SimRobot(cfg.plant, cfg.plant_motor_l, cfg.plant_motor_r,
                              plant_config(cfg, seed), start=start)
        # free-running: the harness keeps to the wall clock on its own (only when paced)
        self.free_running = free_running = paced and free_running
        self.sim = Simavr(elf, paced=free_running)
        self.paced = paced
        self.name = f"fw-{os.getpid()}-{next(_names)}"
        if free_running:
            self.counts = None
            self.url = self.sim.pty  # the harness serves it as the bytes come, as a USB adapter does
        elif paced:
            # The pty's kernel hand-over takes microseconds, or as long as a busy machine's
            # scheduler makes it: wait for it briefly, then go on (a late byte comes with a
            # later read); the harness does not wait for the host's bytes at all. A run on the
            # wall clock is not deterministic anyway, and a long wait would stall the tick.
            self.counts = protocol_simavr.register(self.name, self.sim.pty, wait_s=0.002, strict=False)
            self.url = f"simavr://{self.name}"
        else:
            self.counts = protocol_simavr.register(self.name, self.sim.pty)
            self.url = f"simavr://{self.name}"
        self.mpu = plant_mpu(self.robot, part_by_name(cfg.sim.gyro.part))
        self.i2c = FaultyI2cBus(self.mpu)  # as EmulatedDevices: faults injectable (sim_hal/faults.py)
        robot = self.robot
        self._t0 = robot.t
        self._count = robot.read_encoder()
        self._wheels = robot.read_wheel_counts()
        self._enc_total = 0  # counts the wheel turned since the AVR's power-on
        self._wheel_total = (0, 0)
        self._battery_mv = round(robot.battery_v * 1000)
        self.sim.set_battery(robot.battery_v)
        self._duty = (0.0, 0.0)
        self._closed = False
        self.last: Report | None = None  # the harness's latest report (lockstep), for tests
        self.time = SimTime(lambda: robot.t, self._advance, paced)  # the real drivers' Clock

    def _cycle(self, t: float) -> int:
        return round((t - self._t0) * self.sim.freq)

    def _command(self, mean: tuple[float, float]) -> None:
        dl = min(1.0, max(-1.0, mean[0]))
        dr = min(1.0, max(-1.0, mean[1]))
        if (dl, dr) != self._duty:
            self._duty = (dl, dr)
            self.robot.command(dl, dr)

    def _advance(self, t: float) -> None:
        robot = self.robot
        step = robot.step_s
        if self.free_running:
            t_prev = robot.t
            while robot.t < t - 1e-12:
                robot.advance_to(min(t, robot.t + step))
            if robot.t <= t_prev:
                return
            c = robot.read_encoder()
            d = wrap_i32(c - self._count)
            self._count = c
            self._enc_total += d
            wl, wr = self._wheel_deltas()
            self._wheel_total = (self._wheel_total[0] + wl, self._wheel_total[1] + wr)
            dt = robot.t - t_prev
            wheels = (self._wheel_total[0], wl / dt, self._wheel_total[1], wr / dt) if self.wheel_counts else None
            # Never wait for the harness here: it runs on its own, and a tick must not stall
            # when the OS is slow to schedule it (the firmware's STATE stream is what the host
            # waits for, as with real hardware). The plant takes the newest outputs that came.
            reports = self.sim.replies()
            extra = "" if wheels is None else " " + " ".join(f"{w:.3f}" for w in wheels)
            self.sim.post(f"enc {self._enc_total:.3f} {d / dt:.3f}{extra}")
            if reports:
                self._command(reports[-1].mean)
            return
        counts = self.counts
        while robot.t < t - 1e-12:
            robot.advance_to(min(t, robot.t + step))
            c = robot.read_encoder()
            d = wrap_i32(c - self._count)
            self._count = c
            mv = round(robot.battery_v * 1000)
            battery_mv = mv if mv != self._battery_mv else None
            self._battery_mv = mv
            rep = self.sim.run(self._cycle(robot.t), d, sync=None if self.paced else counts.host_written,
                               wheels=self._wheel_deltas(), battery_mv=battery_mv)
            counts.mcu_sent = rep.tx_total
            self.last = rep
            self._command(rep.mean)

    def _wheel_deltas(self) -> tuple[int, int]:
        """Counts the drive wheels turned since the last call ((0, 0) when not counted)."""
        if not self.wheel_counts:
            return 0, 0
        w = self.robot.read_wheel_counts()
        d = (wrap_i32(w[0] - self._wheels[0]), wrap_i32(w[1] - self._wheels[1]))
        self._wheels = w
        return d

    def set_estop(self, open_: bool) -> None:
        """Open (True) or close the robot's hardware estop input now (lockstep runs)."""
        if self.free_running:
            raise HalIOError("set_estop: lockstep runs only (the free-running harness is busy)")
        self.sim.set_estop(open_)

    def _settle(self) -> None:
        """At close: the host's last bytes (the Bridge's STOP) reach the firmware, and its
        outputs the plant, as they would on a robot whose computer shuts down."""
        if self.free_running:
            deadline = time.monotonic() + 1.0
            while self.sim._posted and time.monotonic() < deadline:
                self.sim.replies()
                time.sleep(0.001)
            time.sleep(0.005)  # the harness runs on its own: give it the STOP's time on the line
            rep = self.sim.out() if not self.sim._posted else None
        else:
            if self.paced:
                time.sleep(0.002)  # the STOP through the pty's kernel hand-over
            rep = self.sim.run(self._cycle(self.robot.t) + self.sim.freq // 200, 0,
                               sync=None if self.paced else self.counts.host_written)
        if rep is not None:
            self._command(rep.inst)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self._settle()
        except HalIOError:
            pass  # the harness is gone already: nothing more reaches the plant
        protocol_simavr.unregister(self.name)
        self.sim.close()


def firmware_for(encoder_cpr: int, wheel_cpr: int) -> Path:
    """The firmware ELF built for these encoders: the default build when they are its
    (8192, no wheels), else a build of its own under firmware/build/cpr-E-W/."""
    if (encoder_cpr, wheel_cpr) == (8192, 0):
        ensure_built("all", "sim")
        return firmware_build.artifact(DEFAULT_ELF)
    sub = f"cpr-{encoder_cpr}-{wheel_cpr}"
    ensure_built("sim")
    try:
        firmware_build.build("all", extra=(f"BUILD=build/{sub}", f"ENCODER_CPR={encoder_cpr}",
                                           f"WHEEL_CPR={wheel_cpr}"))
    except firmware_build.BuildError as e:
        raise HalInitError(str(e)) from None
    return firmware_build.artifact(f"{sub}/{DEFAULT_ELF}")


def _parse_url(url: str) -> tuple[Path | None, bool]:
    """`simavr://[PATH.elf][?free-running]` -> (the firmware, None for the default build;
    whether a paced run lets the harness keep the wall clock itself). PATH is relative to the
    source tree unless absolute."""
    rest = url.split("://", 1)[-1].strip()
    rest, _, query = rest.partition("?")
    free = "free-running" in query.split("&")
    if not rest or not rest.endswith(".elf"):
        return None, free
    path = Path(rest)
    return (path if path.is_absolute() else firmware_build.FIRMWARE_DIR.parent / path), free


def open_firmware_sim_hal(cfg: Config, start: tuple[float, float, float] = (0.0, 0.0, 0.0),
                          seed: int | None = None, paced: bool = False,
                          **_: Any) -> EmulatedRealHal:
    """The `firmware-sim` backend (hal/registry.py): RealHal over FirmwareSimDevices.

    The one place that reads the config's `hal:` section for it: the bridge keys are the
    real backend's, with the URL replaced by the harness's port."""
    elf, free_running = _parse_url(cfg.hal.bridge.url or "")
    devices = FirmwareSimDevices(cfg, start, seed, paced, elf=elf, free_running=free_running)
    real = real_hal_on(cfg, devices)
    # The bridge asks the time for every packet; paced, each ask would bring the plant and
    # the AVR up to the wall clock, a simulation step costs a round trip to the harness, and
    # a burst of asks chases the wall clock instead of catching up with it. It reads the
    # simulated time; RealHal.read (once per tick) and the daemon move it.
    real.encoder.clock = _ReadingClock(devices.time, devices.robot)
    real.encoder.byte_time_s = harness_byte_time_s(cfg.hal.bridge.baudrate)
    return EmulatedRealHal(real, devices)


def harness_byte_time_s(baud: int, f_cpu: int = F_CPU) -> float:
    """A byte's time on the harness's line: the firmware's UART divider for `baud` (U2X mode,
    firmware/Makefile's rounding), and simavr's 11 bit times a byte."""
    ubrr = (f_cpu + 4 * baud) // (8 * baud) - 1
    return 11 * 8 * (ubrr + 1) / f_cpu


class _ReadingClock:
    """A Clock that reads the simulated time without advancing it; sleeping advances it."""

    def __init__(self, time_: SimTime, robot: SimRobot) -> None:
        self._time = time_
        self._robot = robot

    def now(self) -> float:
        return self._robot.t

    def sleep_until(self, deadline: float) -> float:
        return self._time.sleep_until(deadline)


PACED_NICE = -10  # the paced harness's nice value where the OS allows it


def _favour(pid: int) -> None:
    """Run a paced harness ahead of ordinary processes: a real MCU has a CPU of its own, and a
    harness that waits behind the machine's other work misses its STATEs and starves the
    daemon of data (seen: "no new data for 21 ticks" at start-up beside two CPU hogs). Without
    the privilege it runs as it is."""
    try:
        os.setpriority(os.PRIO_PROCESS, pid, PACED_NICE)
    except OSError:
        pass
