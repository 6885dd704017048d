"""The daemon's Foxglove side: a publisher thread, the WebSocket server, MCAP files.

Threads and what each may do:
- The loop thread calls `put` once per tick (VizRing: one struct copy) and, between two
  ticks, `between_ticks` (two attribute checks when nothing is pending), `path_started`.
  It never calls the SDK, never waits on a lock the other threads hold.
- The publisher thread (`ddrt-foxglove`; SCHED_FIFO 1, below the loop, when the loop is
  real-time: rt.raise_gil_helper) takes the ring every
  `interval_s`, builds and logs the messages, forwards log records, rotates MCAP files.
  The SDK queues each client's messages (bounded, oldest dropped), so a slow or stuck
  client costs the publisher nothing either.
- The SDK's threads call the listener: a parameter set is validated there (the reload
  plan, ddrt/viz/params.py) and the plan queued; the loop thread puts it in force through
  the daemon's reload path between two ticks (re-planned there only if the config changed
  meanwhile). Sets beyond SET_BURST at once or SET_RATE_HZ sustained are refused as busy
  before any planning: a client flooding setParameters costs neither the loop nor the GIL. Teleop messages are parsed there and the latest one is
  handed to the loop thread. Nothing a client sends raises out of a callback.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections import deque
from typing import TYPE_CHECKING, Any, Mapping, Protocol

from ddrt.config import Config, ConfigError
from ddrt.viz import params as gains
from ddrt.viz.optional import foxglove
from ddrt.viz.ring import VizRing
from ddrt.viz.teleop import TOPICS as TELEOP_TOPICS, DropLog, parse_twist

if TYPE_CHECKING:
    from hal.base import Hal

log = logging.getLogger("ddrt.viz")
MCAP_FORMATS = ("mcap", "both")  # daemon.telemetry_format's values this service writes (rosbag2: ddrt/ros2)
PENDING_SETS = 4  # parameter sets waiting for the loop; more are refused as busy
SET_RATE_HZ = 10.0  # parameter sets planned per second, sustained (each plan costs ~1.5 ms of CPU)
SET_BURST = 4  # and at once


class VizHost(Protocol):
    """What the service needs from the daemon."""

    cfg: Config

    def apply_overrides(self, overrides: Mapping[str, Any], who: str,
                        planned: tuple[Config, Any] | None = None) -> dict[str, Any]: ...

    def on_teleop(self, v: float, omega: float) -> None: ...

    def fault_text(self) -> str: ...


def check_available(cfg: Config) -> None:
    """At start: a config that asks for Foxglove or MCAP needs the extra (ConfigError naming the key)."""
    d = cfg.daemon
    key = ("daemon.foxglove.enabled: true" if d.foxglove.enabled
           else f"daemon.telemetry_format: {d.telemetry_format}" if d.telemetry_format in MCAP_FORMATS else None)
    if key is not None:
        try:
            foxglove(key)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None


def wanted(cfg: Config) -> bool:
    return cfg.daemon.foxglove.enabled or cfg.daemon.telemetry_format in MCAP_FORMATS


def start_service(host: VizHost, width: int, hal: Hal) -> "VizService | None":
    """The daemon's service as its config asks (None: neither Foxglove nor MCAP)."""
    cfg = host.cfg
    if not wanted(cfg):
        return None
    d = cfg.daemon
    mcap_dir = None
    if d.telemetry_format in MCAP_FORMATS:
        mcap_dir = os.environ.get("LOGS_DIRECTORY") or d.telemetry_dir
        try:
            os.makedirs(mcap_dir, exist_ok=True)
        except OSError as exc:
            log.warning("MCAP telemetry disabled: cannot write to %s: %s", mcap_dir, exc)
            mcap_dir = None
    return VizService(host, width, truth=hal.robot is not None, mcap_dir=mcap_dir)


class LogTap(logging.Handler):
    """ddrt's log records onto /log: `emit` only appends to a bounded deque (any thread)."""

    def __init__(self, maxlen: int = 256) -> None:
        super().__init__(logging.INFO)
        self.records: deque[tuple[float, int, str, str]] = deque(maxlen=maxlen)

    def emit(self, record: logging.LogRecord) -> None:
        try:
            level = 5 if record.levelno >= logging.CRITICAL else 4 if record.levelno >= logging.ERROR \
                else 3 if record.levelno >= logging.WARNING else 2
            self.records.append((record.created, level, record.name, record.getMessage()))
        except Exception:  # noqa: BLE001 - logging must never raise into the caller
            pass


class VizService:
    """The publisher thread, and the server and MCAP files it feeds."""

    def __init__(self, host: VizHost, width: int, *, truth: bool, mcap_dir: str | None,
                 interval_s: float = 0.02) -> None:
        cfg = host.cfg
        fc = cfg.daemon.foxglove
        self.fg = fg = foxglove("daemon.foxglove")
        from ddrt.viz.channels import Channels

        self.host = host
        self.ring = VizRing(width)
        self.context = fg.Context()
        self.channels = Channels(fg, self.context, truth=truth, timing=True)
        self.keys = gains.gain_keys()
        self._offset = time.time() - time.monotonic()  # monotonic tick time -> epoch for Foxglove
        self._paths: deque[tuple[Any, Any]] = deque(maxlen=2)
        self._last_path: tuple[Any, Any] | None = None
        self._sets: deque[tuple[dict[str, Any], Any]] = deque()  # (changes, (base config, plan))
        self._set_lock = threading.Lock()  # the SDK may call back from several threads
        self._set_tokens = float(SET_BURST)
        self._set_refill = time.monotonic()
        self.busy = DropLog(what="foxglove: parameters refused, values kept")
        self._values: tuple[Config, dict[str, float]] | None = None  # the running config's gains
        self._teleop: tuple[float, float] | None = None
        self._teleop_seq = 0
        self._teleop_taken = 0
        self._publish_params = False
        self._last_mono = 0.0  # the last published tick's start (the publisher's phase)
        self.drops = DropLog()
        self.interval_s = interval_s
        self.tap = LogTap()
        logging.getLogger("ddrt").addHandler(self.tap)
        self.mcap = None
        self.server: Any = None
        try:
            if mcap_dir is not None:
                from ddrt.viz.mcapfile import RotatingMcap

                d = cfg.daemon
                self.mcap = RotatingMcap(fg, self.context, mcap_dir, "telemetry", d.telemetry_max_bytes,
                                         d.telemetry_max_files, on_open=self._republish_path)
            if fc.enabled:
                from foxglove.websocket import Capability

                self.server = fg.start_server(
                    name="ddrt", host=fc.host, port=fc.port, context=self.context,
                    capabilities=[Capability.Parameters, Capability.ClientPublish],
                    supported_encodings=["json"], server_listener=_Listener(self))
        except BaseException:
            self._close_sinks()
            raise
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="ddrt-foxglove", daemon=True)
        self._thread.start()
        if self.server is not None:
            log.info("foxglove: serving ws://%s:%d (%d gain parameters)", fc.host, self.server.port, len(self.keys))

    @property
    def port(self) -> int | None:
        return self.server.port if self.server is not None else None

    # ------------------------------------------------------------------ loop thread

    def put(self, row: Any, late_s: float, tick_s: float, mono_s: float, truth: tuple[float, ...] | None) -> None:
        self.ring.put(row, late_s, tick_s, mono_s, truth)

    def path_started(self, path: Any) -> None:
        """A new path is being followed: the publisher sends it (references only, no copy)."""
        self._paths.append((path.x, path.y))

    def between_ticks(self) -> None:
        """Apply what clients asked for: one parameter set, the latest teleop command."""
        if self._teleop_seq != self._teleop_taken:
            self._teleop_taken = self._teleop_seq
            cmd = self._teleop
            if cmd is not None:
                self.host.on_teleop(cmd[0], cmd[1])
        if self._sets:
            changes, planned = self._sets.popleft()
            reply = self.host.apply_overrides(gains.overrides_for(changes, self.keys), "foxglove parameters", planned)
            if not reply.get("ok"):
                log.warning("foxglove: parameters %s not applied, values kept: %s",
                            ", ".join(changes), reply.get("error"))
            self._publish_params = True

    def set_rotation(self, max_bytes: int, max_files: int) -> None:
        if self.mcap is not None:
            self.mcap.set_rotation(max_bytes, max_files)

    # ------------------------------------------------------------------ SDK threads

    def parameters(self, names: list[str] | None = None) -> list[Any]:
        cfg = self.host.cfg
        cached = self._values
        if cached is None or cached[0] is not cfg:  # read off the config once per reload (~70 us)
            cached = self._values = (cfg, gains.values(cfg, self.keys))
        current = cached[1]
        fg = self.fg
        chosen = [n for n in (names or self.keys) if n in current]
        return [fg.Parameter(n, value=current[n], type=fg.ParameterType.Float64) for n in chosen]

    def set_parameters(self, requested: list[Any]) -> list[Any]:
        """Validate a set whole (as a reload would); queue it for the loop, or refuse it."""
        names = [p.name for p in requested]
        with self._set_lock:
            busy = self._busy()
            if busy:
                self.busy.drop(f"{', '.join(map(str, names))}: {busy}")
                return self.parameters(names)
            try:
                changes = {p.name: p.get_value() for p in requested}
                # Over what will be running when the loop takes it: the last waiting set's result.
                try:
                    base = self._sets[-1][1][1].in_force
                except IndexError:
                    base = self.host.cfg
                plan = gains.plan_for(base, changes, self.keys)
            except (ConfigError, ValueError, TypeError, ArithmeticError) as exc:
                log.warning("foxglove: parameters %s refused, values kept: %s", ", ".join(map(str, names)), exc)
                return self.parameters(names)
            self._sets.append((changes, (base, plan)))
        new = gains.values(plan.in_force, self.keys)
        fg = self.fg
        return [fg.Parameter(n, value=new[n], type=fg.ParameterType.Float64) for n in names if n in new]

    def _busy(self) -> str:
        """Why a parameter set is refused before it is planned ('' when it may be): sets
        waiting for the loop, or beyond SET_BURST at once and SET_RATE_HZ sustained (a
        token bucket; a person at a parameter panel sends far fewer)."""
        if len(self._sets) >= PENDING_SETS:
            return f"busy: {PENDING_SETS} parameter sets are waiting for the loop"
        now = time.monotonic()
        self._set_tokens = min(float(SET_BURST), self._set_tokens + (now - self._set_refill) * SET_RATE_HZ)
        self._set_refill = now
        if self._set_tokens < 1.0:
            return f"busy: more than {SET_RATE_HZ:g} parameter sets a second"
        self._set_tokens -= 1.0
        return ""

    def teleop(self, data: bytes) -> None:
        try:
            cmd = parse_twist(data)
        except ValueError as exc:
            self.drops.drop(str(exc))
            return
        self._teleop = cmd
        self._teleop_seq += 1

    # ------------------------------------------------------------------ publisher thread

    def _run(self) -> None:
        from ddrt.runtime.rt import raise_gil_helper

        # Below the loop but above the machine's other work, so it is not preempted holding the GIL.
        why = raise_gil_helper(self.host.cfg.daemon.rt_priority)
        if why:
            log.warning("foxglove publisher: %s (at normal priority)", why)
        # Phase-locked to the loop: wake a quarter period after a tick started, every
        # `interval_s` worth of ticks, so the batch is encoded while the loop sleeps and the
        # two threads do not fight over the GIL during a tick.
        period = 1.0 / self.host.cfg.controller.rate_hz
        every = max(1, round(self.interval_s / period)) * period
        wait = self.interval_s
        while not self._stop.wait(wait):
            try:
                self.publish_once()
            except Exception as exc:  # noqa: BLE001 - the publisher must outlive a bad message
                log.error("foxglove publisher: %s: %s", type(exc).__name__, exc)
            now = time.monotonic()
            anchor = self._last_mono + 0.25 * period
            wait = (anchor + every * (1 + (now - anchor) // every) - now) if self._last_mono else self.interval_s

    def _ns(self, mono_s: float) -> int:
        return int((mono_s + self._offset) * 1e9)

    def publish_once(self) -> None:
        """Everything waiting: ticks, a new path, log records, parameter values, rotation."""
        ch = self.channels
        w = self.ring.width
        fault = self.host.fault_text
        while self._paths:
            self._last_path = self._paths.popleft()
            ch.publish_path(self._last_path[0], self._last_path[1], time.time_ns())
        for rec in self.ring.take():
            truth = rec[w + 3:w + 8] if rec[w + 8] else None
            self._last_mono = rec[w + 2]
            ch.publish_tick(rec[:w], self._ns(rec[w + 2]), truth, (rec[w], rec[w + 1]), fault)
        tap = self.tap.records
        while tap:
            created, level, name, msg = tap.popleft()
            ch.publish_log(level, msg, name, int(created * 1e9))
        if self._publish_params and self.server is not None:
            self._publish_params = False
            self.server.publish_parameter_values(self.parameters())
        if self.mcap is not None:
            self.mcap.check()

    def _republish_path(self) -> None:
        if self._last_path is not None:  # a new MCAP file gets the path it is recording
            self.channels.publish_path(self._last_path[0], self._last_path[1], time.time_ns())

    def close(self) -> None:
        """Publish what is left, finish the MCAP file, stop the server."""
        self._stop.set()
        self._thread.join(5.0)
        try:
            self.publish_once()
        except Exception as exc:  # noqa: BLE001
            log.error("foxglove publisher: %s: %s", type(exc).__name__, exc)
        logging.getLogger("ddrt").removeHandler(self.tap)
        self._close_sinks()

    def _close_sinks(self) -> None:
        if self.mcap is not None:
            self.mcap.close()
        if self.server is not None:
            self.server.stop()


class _Listener:
    """The SDK's ServerListener: every callback returns normally, whatever the client sent."""

    def __init__(self, service: VizService) -> None:
        self.service = service
        self._teleop_channels: dict[tuple[int, int], str] = {}
        self._refused: dict[tuple[int, int], str] = {}

    def on_get_parameters(self, client: Any, param_names: list[str], request_id: str | None = None) -> list[Any]:
        try:
            return self.service.parameters(list(param_names) or None)
        except Exception as exc:  # noqa: BLE001
            log.error("foxglove: getParameters failed: %s: %s", type(exc).__name__, exc)
            return []

    def on_set_parameters(self, client: Any, parameters: list[Any], request_id: str | None = None) -> list[Any]:
        try:
            return self.service.set_parameters(list(parameters))
        except Exception as exc:  # noqa: BLE001
            log.error("foxglove: setParameters failed: %s: %s", type(exc).__name__, exc)
            return []

    def on_client_advertise(self, client: Any, channel: Any) -> None:
        try:
            key = (client.id, channel.id)
            if channel.topic not in TELEOP_TOPICS:
                self._refused[key] = f"topic {channel.topic!r} is not a teleop topic ({', '.join(TELEOP_TOPICS)})"
            elif channel.encoding != "json":
                self._refused[key] = f"{channel.topic}: encoding {channel.encoding!r}, expected json"
            else:
                self._teleop_channels[key] = channel.topic
                log.info("foxglove: client %d publishes teleop on %s", client.id, channel.topic)
        except Exception as exc:  # noqa: BLE001
            log.error("foxglove: advertise failed: %s: %s", type(exc).__name__, exc)

    def on_client_unadvertise(self, client: Any, client_channel_id: int) -> None:
        self._teleop_channels.pop((client.id, client_channel_id), None)
        self._refused.pop((client.id, client_channel_id), None)

    def on_message_data(self, client: Any, client_channel_id: int, data: bytes) -> None:
        try:
            key = (client.id, client_channel_id)
            if key in self._teleop_channels:
                self.service.teleop(bytes(data))
            else:
                self.service.drops.drop(self._refused.get(key, f"unknown client channel {client_channel_id}"))
        except Exception as exc:  # noqa: BLE001
            log.error("foxglove: client message failed: %s: %s", type(exc).__name__, exc)

    def on_subscribe(self, client: Any, channel: Any) -> None:
        return None

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        return None

    def on_parameters_subscribe(self, param_names: list[str]) -> None:
        return None

    def on_parameters_unsubscribe(self, param_names: list[str]) -> None:
        return None
