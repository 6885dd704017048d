"""The physical bound: how long one tick's sensor I/O takes on the real buses, by arithmetic.

No amount of Python speed gets a tick below the time its bytes spend on the wire, so the
compute cost of section 2 only matters next to this. Figures are lower bounds: they leave out
the kernel's driver overhead, clock stretching and the MCU's own response time.
"""

from __future__ import annotations

from dataclasses import dataclass

from hal.mpu6050 import GYRO_ZOUT_H
from hal.wire import DUTY_FULL_SCALE, Drive, Packet, State, encode_frame, encode_packet

I2C_BITS_PER_BYTE = 9  # 8 data bits + ACK/NACK
UART_BITS_PER_BYTE = 10  # start + 8 data + stop (8N1)
USB_FS_BIT_RATE = 12_000_000  # full-speed USB, bit/s
USB_FRAME_S = 0.001  # full-speed frame: a CDC bulk transfer waits at most one frame to be scheduled
# Bits around one bulk data payload: IN/OUT token (SYNC 8 + PID 8 + ADDR/ENDP 11 + CRC5 5 + EOP 3),
# data packet framing (SYNC 8 + PID 8 + CRC16 16 + EOP 3), handshake (SYNC 8 + PID 8 + EOP 3).
USB_BULK_OVERHEAD_BITS = 35 + 35 + 19
USB_WORST_BIT_STUFFING = 7.0 / 6.0  # one stuffed bit after six ones


@dataclass(frozen=True)
class I2cRead:
    """One I2C register read, broken into bit times."""

    clock_hz: float
    register: int
    data_bytes: int
    bits: int
    seconds: float


def i2c_register_read(clock_hz: float, data_bytes: int = 2, register: int = GYRO_ZOUT_H) -> I2cRead:
    """A block read of `data_bytes` starting at one register (e.g. GYRO_ZOUT_H, 0x47):
    START, address+W, register, repeated START, address+R, data bytes, STOP.

    START, repeated START and STOP each take about one bit time; every byte takes nine
    (eight bits plus the ACK or, for the last data byte, the NACK).
    """
    if clock_hz <= 0:
        raise ValueError(f"clock_hz: must be positive, got {clock_hz}")
    if data_bytes < 1:
        raise ValueError(f"data_bytes: must be at least 1, got {data_bytes}")
    conditions = 3  # START, repeated START, STOP
    bytes_on_bus = 3 + data_bytes  # address+W, register, address+R, data
    bits = conditions + I2C_BITS_PER_BYTE * bytes_on_bus
    return I2cRead(clock_hz=clock_hz, register=register, data_bytes=data_bytes, bits=bits, seconds=bits / clock_hz)


@dataclass(frozen=True)
class SerialFrames:
    """Protocol v1 frames of one tick: the DRIVE the host sends and the STATE it receives."""

    drive_raw: int  # packet bytes before COBS
    drive_wire: int  # COBS bytes + the 0x00 delimiter
    state_raw: int
    state_wire: int


def tick_frames() -> SerialFrames:
    """Lengths measured by encoding representative packets with hal.wire's own encoder."""
    drive = Packet(17, Drive(duty_l=DUTY_FULL_SCALE // 3, duty_r=-DUTY_FULL_SCALE // 4, timeout_ms=50))
    state = Packet(42, State(t_us=123_456_789, count=-98_765, flags=0x02, ack_seq=17))
    d_wire = encode_frame(drive)
    s_wire = encode_frame(state)
    return SerialFrames(drive_raw=len(encode_packet(drive)), drive_wire=len(d_wire),
                        state_raw=len(encode_packet(state)), state_wire=len(s_wire))


def uart_seconds(n_bytes: int, baud: float = 115200.0) -> float:
    """Wire time of `n_bytes` on an 8N1 UART."""
    if baud <= 0:
        raise ValueError(f"baud: must be positive, got {baud}")
    return n_bytes * UART_BITS_PER_BYTE / baud


def usb_fs_wire_seconds(n_bytes: int) -> float:
    """Bus time of one small bulk transfer at full speed (token, data, handshake; worst-case
    bit stuffing). Tiny beside the 1 ms frame it has to wait for."""
    bits = (USB_BULK_OVERHEAD_BITS + 8 * n_bytes) * USB_WORST_BIT_STUFFING
    return bits / USB_FS_BIT_RATE


@dataclass(frozen=True)
class IoBound:
    """Everything section 6 prints, in seconds."""

    i2c_100k: I2cRead
    i2c_400k: I2cRead
    frames: SerialFrames
    uart_baud: float
    uart_drive_s: float
    uart_state_s: float
    usb_drive_wire_s: float
    usb_state_wire_s: float

    @property
    def uart_both_s(self) -> float:
        """DRIVE then STATE, one after the other (the sum; a UART is full duplex, so they can overlap)."""
        return self.uart_drive_s + self.uart_state_s

    @property
    def usb_worst_s(self) -> float:
        """Each direction may wait one whole 1 ms frame before its transfer is scheduled."""
        return 2 * USB_FRAME_S + self.usb_drive_wire_s + self.usb_state_wire_s

    @property
    def usb_best_s(self) -> float:
        return self.usb_drive_wire_s + self.usb_state_wire_s


def io_bound(baud: float = 115200.0) -> IoBound:
    frames = tick_frames()
    return IoBound(
        i2c_100k=i2c_register_read(100_000.0),
        i2c_400k=i2c_register_read(400_000.0),
        frames=frames,
        uart_baud=baud,
        uart_drive_s=uart_seconds(frames.drive_wire, baud),
        uart_state_s=uart_seconds(frames.state_wire, baud),
        usb_drive_wire_s=usb_fs_wire_seconds(frames.drive_wire),
        usb_state_wire_s=usb_fs_wire_seconds(frames.state_wire),
    )



def render(b: IoBound, compute_p50_us: float | None, compute_p99_us: float | None, period_s: float) -> list[str]:
    """Section 6: the bus arithmetic, then the bound beside the measured compute."""
    us = 1e6
    f = b.frames
    lines = [
        "Computed, not measured: the time one tick's sensor I/O spends on the wire, from protocol v2 "
        "(docs/protocol.md) and the MPU-6050 register map. Driver and kernel overhead come on top.",
        "",
        "| transfer | size | bus | time (us) |",
        "|---|---|---|---|",
        f"| I2C block read of GYRO_ZOUT_H/L (0x{b.i2c_100k.register:02X}, 2 bytes): START, addr+W, reg, "
        f"repeated START, addr+R, 2 data, STOP, 9 bits per byte | {b.i2c_100k.bits} bit times | 100 kHz | "
        f"{b.i2c_100k.seconds * us:.0f} |",
        f"| the same | {b.i2c_400k.bits} bit times | 400 kHz | {b.i2c_400k.seconds * us:.0f} |",
        f"| DRIVE frame ({f.drive_raw} packet bytes, COBS + 0x00 = {f.drive_wire} bytes, 10 bits each) | "
        f"{f.drive_wire} B | UART {b.uart_baud:.0f} baud | {b.uart_drive_s * us:.0f} |",
        f"| STATE frame ({f.state_raw} packet bytes, COBS + 0x00 = {f.state_wire} bytes) | {f.state_wire} B | "
        f"UART {b.uart_baud:.0f} baud | {b.uart_state_s * us:.0f} |",
        f"| DRIVE + STATE, one after the other | {f.drive_wire + f.state_wire} B | UART {b.uart_baud:.0f} baud | "
        f"{b.uart_both_s * us:.0f} |",
        f"| DRIVE + STATE, bus time only (token, data, handshake, worst bit stuffing) | "
        f"{f.drive_wire + f.state_wire} B | USB full-speed CDC | {b.usb_best_s * us:.0f} |",
        f"| DRIVE + STATE, each waiting up to one 1 ms USB frame | {f.drive_wire + f.state_wire} B | "
        f"USB full-speed CDC | up to {b.usb_worst_s * us:.0f} |",
    ]
    period_us = period_s * us
    if compute_p50_us is not None and compute_p99_us is not None:
        io_uart = b.i2c_400k.seconds * us + b.uart_both_s * us
        io_usb = b.i2c_400k.seconds * us + b.usb_worst_s * us
        lines += [
            "",
            f"Beside it, the measured compute of one tick (section 2, read and write excluded): p50 "
            f"{compute_p50_us:.0f} us, p99 {compute_p99_us:.0f} us. Sensor I/O at 400 kHz I2C plus a UART "
            f"DRIVE and STATE: {io_uart:.0f} us; with USB CDC instead of the UART: up to {io_usb:.0f} us. "
            f"I/O + compute p99 = {io_uart + compute_p99_us:.0f} us (UART) or {io_usb + compute_p99_us:.0f} us (USB) "
            f"of the {period_us:.0f} us period. The serial link is full duplex and the MCU streams STATE on its "
            "own; the host polls the newest buffered STATE without blocking (hal/bridge.py) and its DRIVE goes "
            "to the kernel's buffer, so the frame times are latency added to the loop, not time the tick "
            "waits. The I2C read blocks the tick for its whole duration.",
        ]
    return lines
