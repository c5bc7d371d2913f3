"""What every simulated serial device shares: serving a PTY from a daemon thread (`PtyDevice`), the pyserial
URL handler that opens one on a fresh PTY (`PtySerial`), and the parsing of the URL's options
(`split_url_options`). The DAQ (`simdaq://`) and the automatic hammer (`simhammer://`) are built on them."""
from __future__ import annotations

import abc
import errno
import fcntl
import logging
import os
import select
import threading
import tty
from typing import Any, Callable
from urllib.parse import parse_qsl

import serial
from serial.serialutil import SerialException

from odsplat.spine.errors import InputError

log = logging.getLogger(__name__)


def parse_bool(value: str) -> bool:
    """A URL option's boolean: 1/true/yes/on or 0/false/no/off."""
    if value.lower() in ("1", "true", "yes", "on"):
        return True
    if value.lower() in ("0", "false", "no", "off"):
        return False
    raise ValueError(f"expected 0 or 1, got {value!r}")


def split_url_options(url: str, query: str, options: dict[str, tuple[str, Callable[[str], Any]]],
                      fault_fields: set[str], others: dict[str, str] | None = None
                      ) -> tuple[dict[str, Any], dict[str, Any]]:
    """Parse a device URL's query by `options` (URL key -> (keyword, parser)) into the device's keywords and
    its faults' (the keywords in `fault_fields`). A key not in `options` goes to `others` as it is, or, without
    `others`, is an InputError naming the URL and the keys expected."""
    device_kw: dict[str, Any] = {}
    fault_kw: dict[str, Any] = {}
    for key, value in parse_qsl(query, keep_blank_values=True):
        if key not in options:
            if others is None:
                raise InputError(url, f"unknown option {key!r}; expected one of {sorted(options)}")
            others[key] = value
            continue
        name, parse = options[key]
        try:
            parsed = parse(value)
        except ValueError as e:
            raise InputError(url, f"option {key}={value!r}: {e}") from None
        (fault_kw if name in fault_fields else device_kw)[name] = parsed
    return device_kw, fault_kw


class PtyDevice(abc.ABC):
    """A device on the master side of a PTY pair, served by one daemon thread (`_run`): it selects on the master and
    on a wake-up pipe (close() writes to it), hands what the host wrote to `_on_bytes`, and writes what the device
    queued in `_out`. Subclasses say what happens between selects (`_tick`, returning how long the select may
    sleep, and `_after_io`) and what the host's bytes mean (`_on_bytes`)."""

    def __init__(self, name: str):
        self.pty_name = name
        self.slave_path: str | None = None
        self._out = bytearray()
        self._master = self._slave = self._wake_r = self._wake_w = -1
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def serve_pty(self) -> str:
        """Open a PTY pair, speak the protocol on the master in a daemon thread; returns the slave's path."""
        if self._thread is not None:
            raise InputError(self.pty_name, "already serving")
        self._wake_r, self._wake_w = os.pipe()  # close() wakes the thread through this
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no newline translation: bytes pass unchanged
        # The device keeps the slave open so the master never reads EIO when the host closes and reopens.
        fcntl.fcntl(self._master, fcntl.F_SETFL, fcntl.fcntl(self._master, fcntl.F_GETFL) | os.O_NONBLOCK)
        self.slave_path = os.ttyname(self._slave)
        self._thread = threading.Thread(target=self._run, name=f"{self.pty_name} {self.slave_path}", daemon=True)
        self._thread.start()
        log.info("%s serving on %s", self.pty_name, self.slave_path)
        return self.slave_path

    def close(self) -> None:
        self._stop.set()
        if self._wake_w >= 0:
            os.write(self._wake_w, b"x")
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5)
            if self._thread.is_alive():
                log.error("%s: device thread did not stop", self.pty_name)
        for name in ("_master", "_slave", "_wake_r", "_wake_w"):
            fd = getattr(self, name)
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
                setattr(self, name, -1)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @abc.abstractmethod
    def _tick(self) -> float | None:
        """The device's own work before each select (produce data, fire due events); returns the longest the
        select may then sleep, in seconds (None: until the host writes or close() wakes it)."""

    @abc.abstractmethod
    def _on_bytes(self, data: bytes) -> None:
        """What the host wrote (raw bytes, any chunking)."""

    def _after_io(self) -> None:  # noqa: B027  (an optional hook with a default, not abstract)
        """After each select's reads and writes (default: nothing)."""

    def _run(self) -> None:
        """The device thread's event loop, until `_stop` is set, close() wakes it or `_master` is closed."""
        try:
            while not self._stop.is_set() and self._master >= 0:
                timeout = self._tick()
                want_write = [self._master] if self._out else []
                readable, writable, _ = select.select([self._master, self._wake_r], want_write, [], timeout)
                if self._wake_r in readable:
                    break
                if self._master in readable:
                    try:
                        data = os.read(self._master, 65536)
                    except BlockingIOError:
                        data = None
                    if data is not None:
                        self._on_bytes(data)
                if self._master in writable and self._out:
                    self._send()
                self._after_io()
        except Exception:
            log.exception("%s: device thread failed", self.pty_name)
            if self._master >= 0:  # the host then sees a disconnect instead of silence
                os.close(self._master)
                self._master = -1

    def _send(self) -> None:
        try:
            n = os.write(self._master, self._out[:65536])
        except BlockingIOError:
            return
        except OSError as e:
            if e.errno != errno.EIO:  # EIO: no slave open right now; keep the data for the next reader
                raise
            return
        del self._out[:n]


class PtySerial(serial.Serial):
    """A real POSIX serial port on the PTY slave of a device built from the URL; the device runs until close().
    Subclasses (each module's `Serial`, found through `serial.protocol_handler_packages`) set `device_from_url`."""

    device_from_url = None  # staticmethod: url -> PtyDevice, not yet serving

    def __init__(self, *args, **kwargs):
        self.device: PtyDevice | None = None
        super().__init__(*args, **kwargs)

    def open(self) -> None:
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        if self.is_open:
            raise SerialException("Port is already open.")
        url = self._port
        self.device = type(self).device_from_url(url)
        slave = self.device.serve_pty()
        self.portstr = slave  # PosixSerial.open() opens portstr; name and messages keep the URL
        try:
            super().open()
        except Exception:
            self.device.close()
            self.device = None
            raise
        finally:
            self.portstr = url
        log.info("%s open on %s", url, slave)

    def close(self) -> None:
        super().close()
        if self.device is not None:
            self.device.close()
            self.device = None
