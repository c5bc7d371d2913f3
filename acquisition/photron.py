"""Photron FASTCAM cameras through PDCLIB (Photron Device Control SDK), loaded with ctypes only when a
`PhotronCamera` is made, so that importing odsplat never needs the SDK.

The module has two halves. The pure half (parameter mapping, the recording window, frame unpacking,
status and error names) is plain Python and numpy and is tested. The SDK half (`load_pdclib`,
`PhotronCamera`) calls PDCLIB and has never been run against a camera: see docs/cameras.md.

What comes from where:
- Function signatures and constants are taken from Photron's SDK headers (PDCFUNC.h, PDCVALUE.h,
  PDCERROR.h, PDCDEV.h, PDCSTR.h; (C) 2006-2012 Photron) as republished in public projects (the EPICS
  areaDetector driver ADPhotron, PyPhotron). They are transcribed, not checked against a DLL.
- Behaviours no header states (when a recording is over, what "after frames" counts, how a 12-bit
  pixel sits in a 16-bit transfer) are guesses, collected in `SdkAssumptions` below.
- The trigger-mode encoding (mode << 24) is corroborated by real files: ball_12bit.cihx in
  ../shared/data records `pdcMode` 117440512 = 0x07000000, PDC_TRIGGER_RANDOM_MANUAL.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import ipaddress
import logging
import os
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from os import PathLike
from pathlib import Path

import numpy as np

from odsplat.spine.errors import InputError, OdsplatError
from odsplat.spine.io.mraw import unpack_12bit
from odsplat.spine.manifest import CameraInfo

from .camera import CameraTimeout, Frame, RecordingStatus, TriggerSettings

log = logging.getLogger(__name__)

LIBRARY_ENV = "ODSPLAT_PDCLIB"  # a path to PDCLIB.dll / libPDCLIB.so, tried before the system search


# ============================================================ what we take from Photron's headers

@dataclass(frozen=True)
class PdcConstants:
    """Values transcribed from PDCERROR.h, PDCVALUE.h and PDCDEV.h (not checked against a DLL)."""

    SUCCEEDED: int = 1                 # every PDC_ function returns PDC_SUCCEEDED or PDC_FAILED
    FAILED: int = 0
    MAX_DEVICE: int = 64               # PDC_DETECT_NUM_INFO holds this many PDC_DETECT_INFO
    MAX_LIST_NUMBER: int = 256         # the PDC_Get...List functions fill at most this many values
    MAX_STRING_LENGTH: int = 256
    INTTYPE_G_ETHER: int = 0x02        # Gigabit Ethernet interface
    DETECT_NORMAL: int = 0             # look at the given IP address only (PDC_DETECT_AUTO = 1 scans)
    COLORTYPE_MONO: int = 0
    COLORTYPE_COLOR: int = 1
    STATUS_LIVE: int = 0x00
    STATUS_PLAYBACK: int = 0x01
    STATUS_RECREADY: int = 0x02
    STATUS_ENDLESS: int = 0x04
    STATUS_REC: int = 0x08
    STATUS_SAVE: int = 0x10
    STATUS_LOAD: int = 0x20
    STATUS_PAUSE: int = 0x40
    STATUS_STORAGE_PLAYBACK: int = 0x80
    TRIGGER_START: int = 0x00 << 24
    TRIGGER_CENTER: int = 0x01 << 24
    TRIGGER_END: int = 0x02 << 24
    TRIGGER_RANDOM: int = 0x03 << 24
    TRIGGER_MANUAL: int = 0x04 << 24
    ERROR_INITIALIZED: int = 7         # PDC_Init called twice in one process
    ERROR_DROP_FRAME: int = 22         # "frame is not captured": a dropped frame


PDC = PdcConstants()

# PDCERROR.h, with the header's own wording (lightly corrected).
ERROR_MESSAGES: dict[int, str] = {
    1: "no error", 2: "PDCLIB not initialised", 3: "illegal device number", 4: "illegal child number",
    5: "illegal parameter", 6: "memory allocation failed", 7: "already initialised", 8: "device not found",
    9: "timed out", 10: "function failed", 11: "function disabled", 12: "no recorded data",
    13: "unknown frame number", 14: "camera mode error", 15: "not recording in endless mode",
    16: "file read failed", 17: "file write failed", 18: "image size error", 19: "frame area error",
    20: "play mode error", 21: "not supported", 22: "frame not captured (dropped)",
    23: "file already open", 24: "file not open", 25: "string conversion failed",
    100: "module load failed", 101: "module free failed", 102: "module already loaded",
    103: "module not loaded", 104: "device not yet detected", 105: "too many device kinds",
    106: "initialisation failed", 107: "device already open", 108: "device not open",
    110: "camera cannot enter live mode", 111: "camera cannot enter playback mode",
    112: "camera cannot enter FAST Drive playback mode", 113: "device not connected",
    114: "ICMP timeout", 200: "send error", 201: "receive error", 202: "interface re-initialisation failed",
    203: "command error", 204: "compare data error", 300: "FPGA configuration failed",
    301: "register access failed", 400: "FAST Drive / SD card access failed",
    401: "unusual FAST Drive / SD card data", 402: "no storage card", 403: "storage write failed",
    404: "storage read failed", 405: "storage size error", 406: "storage format error",
    407: "storage locked by password", 408: "invalid storage password", 409: "storage is downloading",
    500: "detection disabled while a multi-head (TX) device is open", 501: "partition locked",
    502: "initial error",
}

STATUS_NAMES: dict[int, str] = {
    PDC.STATUS_LIVE: "live", PDC.STATUS_PLAYBACK: "playback", PDC.STATUS_RECREADY: "ready to record",
    PDC.STATUS_ENDLESS: "recording endlessly (waiting for the trigger)", PDC.STATUS_REC: "recording",
    PDC.STATUS_SAVE: "saving", PDC.STATUS_LOAD: "loading", PDC.STATUS_PAUSE: "paused",
    PDC.STATUS_STORAGE_PLAYBACK: "storage playback",
}


# ============================================================ what no header says (UNVERIFIED)

@dataclass(frozen=True)
class SdkAssumptions:
    """UNVERIFIED: behaviours of PDCLIB and the cameras that this driver relies on but that no header
    states. Each is a guess from public driver code or from Photron's file formats; the first run on a
    camera should confirm or correct each one (docs/cameras.md says how)."""

    # PDC_GetMemImageData's nBitDepth for cameras deeper than 8 bits: 16, as ADPhotron does.
    deep_transfer_bits: int = 16
    # A 12-bit pixel in a 16-bit transfer sits in the low bits, as PFV writes .mraw files
    # ("EffectiveBit Side: Lower" in the cihx of beam.mraw). frames() warns when a value says otherwise.
    deep_transfer_low_aligned: bool = True
    # A transfer of nBitDepth 12 (only when asked for with transfer_bits=12) is packed as in .mraw:
    # two pixels in three bytes, big-endian. Whether PDCLIB offers 12 at all is unknown.
    packed12_like_mraw: bool = True
    # The recording is over when the status leaves RECREADY/ENDLESS/REC for LIVE (ADPhotron waits for
    # LIVE) or PLAYBACK (cameras with auto-play).
    done_statuses: tuple[int, ...] = (PDC.STATUS_LIVE, PDC.STATUS_PLAYBACK)
    # CENTER, END and MANUAL need PDC_SetEndless after PDC_SetRecReady to fill the pretrigger
    # memory; START does not (ADPhotron).
    endless_modes: tuple[int, ...] = (PDC.TRIGGER_CENTER, PDC.TRIGGER_END, PDC.TRIGGER_MANUAL)
    # MANUAL's after-frames count includes the trigger frame. select_window() reports honestly either
    # way; a wrong guess only costs one frame at the end.
    after_frames_include_trigger: bool = True
    # PDC_SetStatus(LIVE) aborts a recording that is armed or running.
    abort_status: int = PDC.STATUS_LIVE
    # The device name is read with child number 0 (the device itself rather than a head).
    name_child: int = 0
    # The first child listed by PDC_GetExistChildDeviceList is the head to use; 1 when none is listed.
    default_child: int = 1
    # How often wait() asks PDC_GetStatus.
    poll_s: float = 0.01


ASSUMPTIONS = SdkAssumptions()


# ============================================================ pure parts: parameter mapping

def ip_to_pdc(ip: str) -> int:
    """The IPv4 address as PDC_DetectDevice wants it: an unsigned long in host order (192.168.0.10 ->
    0xC0A8000A)."""
    try:
        return int(ipaddress.IPv4Address(str(ip).strip()))
    except ValueError:
        raise InputError("PhotronCamera.ip", f"expected an IPv4 address such as 192.168.0.10, got {ip!r}") from None


def choose_record_rate(requested_fps: float, supported: Sequence[int], *, rel_tol: float = 0.01) -> int:
    """The supported record rate nearest to `requested_fps`; an error when none lies within `rel_tol`
    (the rates a camera offers depend on its resolution, so the message lists the neighbours)."""
    rates = sorted({int(r) for r in supported if int(r) > 0})
    if not rates:
        raise InputError("PDC_GetRecordRateList", "the camera reported no record rates")
    best = min(rates, key=lambda r: (abs(r - requested_fps), r))
    if abs(best - requested_fps) > rel_tol * requested_fps:
        below = [r for r in rates if r < requested_fps][-1:]
        above = [r for r in rates if r > requested_fps][:1]
        near = " and ".join(f"{r} fps" for r in below + above)
        raise InputError("TriggerSettings.fps",
                         f"{requested_fps:g} fps is not a record rate of this camera at its current resolution "
                         f"(range {rates[0]} to {rates[-1]} fps); the nearest are {near}")
    if best != requested_fps:
        log.info("record rate %g fps -> %d fps, the nearest the camera offers", requested_fps, best)
    return best


def choose_shutter(exposure_s: float, supported_fps: Sequence[int], record_rate: int) -> int:
    """The shutter (as 1/s, what PDC_SetShutterSpeedFps takes) with the longest exposure not longer than
    `exposure_s`. Never longer: the exposure is a cap on motion blur, and it cannot exceed the frame
    period 1/record_rate."""
    if exposure_s * record_rate > 1.0 + 1e-9:
        raise InputError("TriggerSettings.exposure_s", f"{exposure_s:g} s is longer than the frame period "
                                                       f"1/{record_rate} s = {1.0 / record_rate:.3g} s")
    shutters = sorted({int(v) for v in supported_fps if int(v) >= record_rate})
    if not shutters:
        raise InputError("PDC_GetShutterSpeedFpsList", f"the camera reported no shutter speed for {record_rate} fps")
    fitting = [v for v in shutters if 1.0 / v <= exposure_s * (1.0 + 1e-9)]
    if not fitting:
        raise InputError("TriggerSettings.exposure_s", f"{exposure_s:g} s is shorter than the shortest shutter of "
                                                       f"this camera, 1/{shutters[-1]} s = {1.0 / shutters[-1]:.3g} s")
    best = fitting[0]
    if abs(1.0 / best - exposure_s) > 1e-6 * exposure_s:
        log.info("exposure %g s -> 1/%d s = %.4g s, the longest the camera offers within it",
                 exposure_s, best, 1.0 / best)
    return best


@dataclass(frozen=True)
class TriggerPlan:
    """How a `TriggerSettings` becomes PDC_SetTriggerMode arguments and an arm sequence."""

    mode_code: int           # PDC_TRIGGER_START / CENTER / END / MANUAL
    after_frames: int        # nAFrames: frames recorded from the trigger on (MANUAL only; 0 otherwise)
    endless: bool            # PDC_SetEndless after PDC_SetRecReady
    pretrigger_frames: int   # wanted before the trigger frame
    post_frames: int         # wanted from the trigger frame on, the trigger frame included
    n_frames: int

    @property
    def mode_name(self) -> str:
        return {PDC.TRIGGER_START: "start", PDC.TRIGGER_CENTER: "center", PDC.TRIGGER_END: "end",
                PDC.TRIGGER_MANUAL: "manual"}.get(self.mode_code, f"0x{self.mode_code:08x}")


def plan_trigger(settings: TriggerSettings, max_frames: int) -> TriggerPlan:
    """Start, center and end use the camera's own modes only when the recording fills its memory
    (`max_frames` at this resolution and rate); any shorter recording uses MANUAL with `n_frames -
    pretrigger` after-frames, so the camera stops as soon as the recording is complete instead of
    filling the whole memory (seconds to minutes at low rates)."""
    if max_frames < 1:
        raise InputError("PDC_GetMaxFrames", f"the camera reported {max_frames} frames of memory")
    n, pre = settings.n_frames, settings.pretrigger_frames
    if n > max_frames:
        raise InputError("TriggerSettings.n_frames", f"the camera holds at most {max_frames} frames at this "
                                                     f"resolution and record rate, {n} were asked for")
    post = n - pre
    native = {"start": PDC.TRIGGER_START, "center": PDC.TRIGGER_CENTER, "end": PDC.TRIGGER_END}
    if n == max_frames and isinstance(settings.pretrigger, str):
        mode, after = native[settings.pretrigger], 0
    else:
        mode = PDC.TRIGGER_MANUAL
        after = post if ASSUMPTIONS.after_frames_include_trigger else post - 1
    return TriggerPlan(mode_code=mode, after_frames=after, endless=mode in ASSUMPTIONS.endless_modes,
                       pretrigger_frames=pre, post_frames=post, n_frames=n)


@dataclass(frozen=True)
class RecordingWindow:
    """The camera frame numbers to download: PDC_GetMemFrameInfo's range cut to what was asked for."""

    trigger_frame: int
    first_frame: int
    last_frame: int

    @property
    def n_frames(self) -> int:
        return max(0, self.last_frame - self.first_frame + 1)

    @property
    def first_counter(self) -> int:
        return self.first_frame - self.trigger_frame

    @property
    def pretrigger_available(self) -> int:
        return max(0, self.trigger_frame - self.first_frame)


def select_window(start: int, end: int, trigger: int, pretrigger: int, post_frames: int) -> RecordingWindow:
    """Frames `trigger - pretrigger .. trigger + post_frames - 1`, cut to the memory's `start..end`:
    fewer pretrigger frames when the camera was armed too shortly before the trigger, fewer after it
    when the recording stopped early. Never padded."""
    if not start <= trigger <= end:
        raise InputError("PDC_GetMemFrameInfo",
                         f"trigger frame {trigger} lies outside the recorded frames {start}..{end}")
    return RecordingWindow(trigger_frame=trigger, first_frame=max(start, trigger - pretrigger),
                           last_frame=min(end, trigger + post_frames - 1))


# ============================================================ pure parts: frame unpacking

def frame_bytes(width: int, height: int, bits: int) -> int:
    """Bytes of one mono frame as PDC_GetMemImageData writes it for nBitDepth `bits`."""
    n = width * height
    if bits == 8:
        return n
    if bits == 16:
        return 2 * n
    if bits == 12:
        if n % 2:
            raise InputError("transfer_bits", f"packed 12-bit frames of {width}x{height} do not fill whole bytes")
        return 3 * n // 2
    raise InputError("transfer_bits", f"expected 8, 12 (packed) or 16, got {bits}")


def unpack_frame(raw: np.ndarray | bytes, width: int, height: int, bits: int) -> np.ndarray:
    """One mono frame from PDC_GetMemImageData's buffer: (height, width) uint8 for 8 bits, uint16 for 16
    (host byte order, as the SDK writes memory) and for packed 12 bits. Always a fresh array."""
    data = np.frombuffer(raw, dtype=np.uint8) if isinstance(raw, (bytes, bytearray, memoryview)) \
        else np.asarray(raw).reshape(-1).view(np.uint8)
    expected = frame_bytes(width, height, bits)
    if data.size != expected:
        raise InputError("PDC_GetMemImageData", f"{data.size} bytes for a {width}x{height} frame of {bits} bits; "
                                                f"expected {expected}")
    if bits == 8:
        return data.reshape(height, width).copy()
    if bits == 16:
        return data.view(np.uint16).reshape(height, width).copy()
    return unpack_12bit(data).reshape(height, width)


# ============================================================ pure parts: names

def status_name(code: int) -> str:
    return STATUS_NAMES.get(int(code), f"unknown status 0x{int(code):02x}")


def error_message(code: int) -> str:
    return ERROR_MESSAGES.get(int(code), "unknown error")


class PdcError(InputError):
    """A PDCLIB function returned PDC_FAILED; `code` is its error code (PDCERROR.h)."""

    def __init__(self, camera: str, function: str, code: int):
        self.function = function
        self.code = int(code)
        super().__init__(camera, f"{function} failed with error {self.code} ({error_message(self.code)})")


# ============================================================ the SDK: structures and signatures

class PDC_DETECT_INFO(ctypes.Structure):  # noqa: N801  (the SDK's name)
    _pack_ = 4
    _fields_ = [("m_nDeviceCode", ctypes.c_ulong), ("m_nTmpDeviceNo", ctypes.c_ulong),
                ("m_nInterfaceCode", ctypes.c_ulong)]


class PDC_DETECT_NUM_INFO(ctypes.Structure):  # noqa: N801
    _pack_ = 4
    _fields_ = [("m_nDeviceNum", ctypes.c_ulong), ("m_DetectInfo", PDC_DETECT_INFO * PDC.MAX_DEVICE)]


class PDC_FRAME_INFO(ctypes.Structure):  # noqa: N801
    _pack_ = 4
    _fields_ = [("m_nStart", ctypes.c_long), ("m_nEnd", ctypes.c_long), ("m_nTrigger", ctypes.c_long),
                ("m_nTwoStageLowToHigh", ctypes.c_long), ("m_nTwoStageHighToLow", ctypes.c_long),
                ("m_nTwoStageTiming", ctypes.c_ulong), ("m_nEvent", ctypes.c_long * 10),
                ("m_nEventCount", ctypes.c_ulong), ("m_nRecordedFrames", ctypes.c_ulong)]


_UL = ctypes.c_ulong
_PUL = ctypes.POINTER(ctypes.c_ulong)
_PCHAR = ctypes.POINTER(ctypes.c_ubyte)  # `char *` out-parameters holding one small number (bit depth, colour type)

# Argument types from PDCFUNC.h; every function returns unsigned long and ends with `unsigned long
# *pErrorCode`, which _Pdc appends.
SIGNATURES: dict[str, tuple] = {
    "PDC_Init": (),
    "PDC_DetectDevice": (_UL, _PUL, _UL, _UL, ctypes.POINTER(PDC_DETECT_NUM_INFO)),
    "PDC_OpenDevice": (ctypes.POINTER(PDC_DETECT_INFO), _PUL),
    "PDC_CloseDevice": (_UL,),
    "PDC_GetDeviceNameA": (_UL, _UL, ctypes.c_char_p),
    "PDC_GetExistChildDeviceList": (_UL, _PUL, _PUL),
    "PDC_GetStatus": (_UL, _PUL),
    "PDC_SetStatus": (_UL, _UL),
    "PDC_GetColorType": (_UL, _UL, _PCHAR),
    "PDC_GetMaxBitDepth": (_UL, _UL, _PCHAR),
    "PDC_GetBitDepth": (_UL, _UL, _PCHAR),
    "PDC_GetResolution": (_UL, _UL, _PUL, _PUL),
    "PDC_GetRecordRate": (_UL, _UL, _PUL),
    "PDC_GetRecordRateList": (_UL, _UL, _PUL, _PUL),
    "PDC_SetRecordRate": (_UL, _UL, _UL),
    "PDC_GetShutterSpeedFps": (_UL, _UL, _PUL),
    "PDC_GetShutterSpeedFpsList": (_UL, _UL, _PUL, _PUL),
    "PDC_SetShutterSpeedFps": (_UL, _UL, _UL),
    "PDC_GetMaxFrames": (_UL, _UL, _PUL, _PUL),
    "PDC_SetTriggerMode": (_UL, _UL, _UL, _UL, _UL),
    "PDC_SetRecReady": (_UL,),
    "PDC_SetEndless": (_UL,),
    "PDC_TriggerIn": (_UL,),
    "PDC_GetMemFrameInfo": (_UL, _UL, ctypes.POINTER(PDC_FRAME_INFO)),
    "PDC_GetMemResolution": (_UL, _UL, _PUL, _PUL),
    "PDC_GetMemRecordRate": (_UL, _UL, _PUL),
    "PDC_GetMemBitDepth": (_UL, _UL, _PCHAR),
    "PDC_GetMemShutterSpeedFps": (_UL, _UL, _PUL),
    "PDC_GetMemImageData": (_UL, _UL, ctypes.c_long, _UL, ctypes.c_void_p),
}


def _library_candidates(library: str | PathLike | None) -> list[str]:
    if library is not None:
        return [str(library)]
    env = os.environ.get(LIBRARY_ENV)
    if env:
        return [env]
    names = ["PDCLIB.dll"] if os.name == "nt" else ["libPDCLIB.so"]
    found = ctypes.util.find_library("PDCLIB")
    if found and found not in names:
        names.append(found)
    return names


def load_pdclib(library: str | PathLike | None = None) -> ctypes.CDLL:
    """Load PDCLIB: `library` if given, else $ODSPLAT_PDCLIB, else the system's search for PDCLIB.dll
    (Windows) or libPDCLIB.so. InputError naming every place tried when none loads."""
    tried = []
    loader = getattr(ctypes, "WinDLL", ctypes.CDLL) if os.name == "nt" else ctypes.CDLL  # WINAPI is stdcall
    for candidate in _library_candidates(library):
        path = Path(candidate)
        if os.name == "nt" and path.parent != Path(".") and path.parent.is_dir():
            os.add_dll_directory(str(path.parent.resolve()))  # PDCLIB.dll loads its per-model DLLs beside it
        try:
            lib = loader(candidate)
        except OSError as exc:
            tried.append(f"{candidate} ({exc})")
            continue
        for function, argtypes in SIGNATURES.items():
            fn = getattr(lib, function, None)
            if fn is not None:
                fn.argtypes = [*argtypes, _PUL]
                fn.restype = ctypes.c_ulong
        log.info("loaded PDCLIB from %s", candidate)
        return lib
    how = (f"pass library= or set {LIBRARY_ENV} to its path" if library is None and not os.environ.get(LIBRARY_ENV)
           else "check the path")
    raise InputError("PDCLIB (Photron SDK)", f"not found; tried {'; '.join(tried)}. Install Photron's SDK "
                                             f"(PDCLIB.dll on Windows, libPDCLIB.so on Linux) and {how}")


class _Pdc:
    """Calls PDCLIB functions by name and turns PDC_FAILED into a PdcError naming the camera."""

    def __init__(self, lib: ctypes.CDLL, camera: str):
        self._lib = lib
        self._camera = camera

    def __call__(self, function: str, *args: object) -> None:
        fn = getattr(self._lib, function, None)
        if fn is None:
            raise InputError(self._camera, f"the loaded PDCLIB has no {function}; it is older than this driver needs")
        error = ctypes.c_ulong(0)
        if fn(*args, ctypes.byref(error)) != PDC.SUCCEEDED:
            raise PdcError(self._camera, function, error.value)

    def ulongs(self, function: str, *args: object, n: int) -> list[int]:
        out = [ctypes.c_ulong(0) for _ in range(n)]
        self(function, *args, *(ctypes.byref(o) for o in out))
        return [o.value for o in out]

    def small(self, function: str, *args: object) -> int:
        """A `char *` out-parameter holding one number."""
        out = ctypes.c_ubyte(0)
        self(function, *args, ctypes.byref(out))
        return out.value

    def list_values(self, function: str, *args: object) -> list[int]:
        size = ctypes.c_ulong(0)
        values = (ctypes.c_ulong * PDC.MAX_LIST_NUMBER)()
        self(function, *args, ctypes.byref(size), values)
        return [int(values[i]) for i in range(min(size.value, PDC.MAX_LIST_NUMBER))]


_INITIALISED: set[int] = set()  # handles of PDCLIB copies on which PDC_Init has run (once per process)


# ============================================================ the driver

@dataclass(frozen=True)
class _Memory:
    """What the camera's memory holds after a recording."""

    width: int
    height: int
    record_rate: int
    bit_depth: int
    window: RecordingWindow


class PhotronCamera:
    """A Photron FASTCAM on Gigabit Ethernet at `ip`, through PDCLIB. Mono heads only.

    Frames download as uint8 for 8-bit recordings and uint16 otherwise; `transfer_bits` (8, 12 or 16)
    overrides the transfer depth. Never run on a camera: see docs/cameras.md before trusting it.
    Call it from one thread; PDCLIB's thread safety is not documented.
    """

    def __init__(self, ip: str, *, library: str | PathLike | None = None, name: str | None = None,
                 transfer_bits: int | None = None):
        self.ip = str(ip)
        self._ip_code = ip_to_pdc(ip)
        self.name = name or f"photron:{self.ip}"
        if transfer_bits not in (None, 8, 12, 16):
            raise InputError("PhotronCamera.transfer_bits", f"expected 8, 12 (packed) or 16, got {transfer_bits!r}")
        self._lib = load_pdclib(library)
        self._pdc = _Pdc(self._lib, self.name)
        self._device: int | None = None
        self._child = ASSUMPTIONS.default_child
        self._transfer_override = transfer_bits
        self._settings: TriggerSettings | None = None
        self._plan: TriggerPlan | None = None
        self._memory: _Memory | None = None
        self._armed = False
        self._dropped: list[int] = []
        try:
            self._open()
            self._read_state()
        except BaseException:
            try:
                self.close()
            except Exception:  # the first error is the one to report
                log.warning("%s: closing after a failed open failed too", self.name, exc_info=True)
            raise

    # -- connection ----------------------------------------------------------------------------

    def _open(self) -> None:
        handle = getattr(self._lib, "_handle", id(self._lib))
        if handle not in _INITIALISED:
            try:
                self._pdc("PDC_Init")
            except PdcError as exc:
                if exc.code != PDC.ERROR_INITIALIZED:
                    raise
            _INITIALISED.add(handle)
        ip_list = (ctypes.c_ulong * PDC.MAX_DEVICE)()
        ip_list[0] = self._ip_code
        found = PDC_DETECT_NUM_INFO()
        self._pdc("PDC_DetectDevice", PDC.INTTYPE_G_ETHER, ip_list, 1, PDC.DETECT_NORMAL, ctypes.byref(found))
        if found.m_nDeviceNum < 1 or found.m_DetectInfo[0].m_nTmpDeviceNo != self._ip_code:
            raise InputError(self.name, f"no Photron camera answered at {self.ip} on Gigabit Ethernet; check the "
                                        "cable, the address and that PFV is not connected to the camera")
        device = ctypes.c_ulong(0)
        self._pdc("PDC_OpenDevice", ctypes.byref(found.m_DetectInfo[0]), ctypes.byref(device))
        self._device = device.value
        try:
            children = self._pdc.list_values("PDC_GetExistChildDeviceList", self._device)
        except PdcError:
            children = []
        self._child = children[0] if children else ASSUMPTIONS.default_child
        name = ctypes.create_string_buffer(PDC.MAX_STRING_LENGTH)
        try:
            self._pdc("PDC_GetDeviceNameA", self._device, ASSUMPTIONS.name_child, name)
            self._model = name.value.decode("ascii", "replace").strip() or "FASTCAM"
        except PdcError:
            self._model = "FASTCAM"
        if self._status() == PDC.STATUS_PLAYBACK:
            self._pdc("PDC_SetStatus", self._device, PDC.STATUS_LIVE)
        log.info("%s: opened %s (device %d, child %d)", self.name, self._model, self._device, self._child)

    def _read_state(self) -> None:
        dev, child = self._device, self._child
        try:
            colour_type = self._pdc.small("PDC_GetColorType", dev, child)
        except PdcError as exc:
            log.warning("%s: %s; taking the head to be mono", self.name, exc.problem)
            colour_type = PDC.COLORTYPE_MONO
        if colour_type != PDC.COLORTYPE_MONO:
            raise InputError(self.name, "is a colour camera; this driver downloads mono frames only")
        self._width, self._height = self._pdc.ulongs("PDC_GetResolution", dev, child, n=2)
        (self._record_rate,) = self._pdc.ulongs("PDC_GetRecordRate", dev, child, n=1)
        (self._shutter_fps,) = self._pdc.ulongs("PDC_GetShutterSpeedFps", dev, child, n=1)
        try:
            self._bit_depth = self._pdc.small("PDC_GetBitDepth", dev, child)
        except PdcError:  # models without a selectable depth answer only the maximum
            self._bit_depth = self._pdc.small("PDC_GetMaxBitDepth", dev, child)

    def _status(self) -> int:
        (status,) = self._pdc.ulongs("PDC_GetStatus", self._device, n=1)
        return status

    def _transfer_bits(self, bit_depth: int) -> int:
        if self._transfer_override is not None:
            return self._transfer_override
        return 8 if bit_depth <= 8 else ASSUMPTIONS.deep_transfer_bits

    # -- data logic: what the camera is ---------------------------------------------------------

    @property
    def frame_shape(self) -> tuple[int, ...]:
        return (self._height, self._width)

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(np.uint8 if self._transfer_bits(self._bit_depth) == 8 else np.uint16)

    def describe(self) -> CameraInfo:
        return CameraInfo(model=f"Photron {self._model}", width_px=self._width, height_px=self._height,
                          fps=float(self._record_rate), bit_depth=self._bit_depth, n_colors=1,
                          exposure_s=1.0 / self._shutter_fps if self._shutter_fps else None)

    # -- trigger logic -------------------------------------------------------------------------

    def configure(self, settings: TriggerSettings) -> None:
        if self._armed:
            raise OdsplatError(f"{self.name}: configure() while armed; stop() first")
        dev, child = self._device, self._child
        self._memory = None  # leaving playback gives up the last recording
        if self._status() != PDC.STATUS_LIVE:
            self._pdc("PDC_SetStatus", dev, PDC.STATUS_LIVE)
        if settings.fps is not None:
            rate = choose_record_rate(settings.fps, self._pdc.list_values("PDC_GetRecordRateList", dev, child))
            self._pdc("PDC_SetRecordRate", dev, child, rate)
        if settings.exposure_s is not None:
            (rate,) = self._pdc.ulongs("PDC_GetRecordRate", dev, child, n=1)
            shutters = self._pdc.list_values("PDC_GetShutterSpeedFpsList", dev, child)
            shutter = choose_shutter(settings.exposure_s, shutters, rate)
            self._pdc("PDC_SetShutterSpeedFps", dev, child, shutter)
        self._read_state()  # the resolution can follow the record rate
        max_frames, _blocks = self._pdc.ulongs("PDC_GetMaxFrames", dev, child, n=2)
        plan = plan_trigger(settings, max_frames)
        self._pdc("PDC_SetTriggerMode", dev, plan.mode_code, plan.after_frames, 0, 0)
        self._settings, self._plan = settings, plan
        log.info("%s: %d fps, shutter 1/%d s, %dx%d, %d-bit; trigger %s, %d after-frames of %d in memory",
                 self.name, self._record_rate, self._shutter_fps, self._width, self._height, self._bit_depth,
                 plan.mode_name, plan.after_frames, max_frames)

    def software_trigger(self) -> None:
        """A trigger from the host (PDC_TriggerIn), for when no TTL edge reaches the camera."""
        if not self._armed:
            raise OdsplatError(f"{self.name}: software_trigger() before arm()")
        self._pdc("PDC_TriggerIn", self._device)

    # -- acquire logic -------------------------------------------------------------------------

    def arm(self) -> None:
        if self._plan is None or self._settings is None:
            raise OdsplatError(f"{self.name}: arm() before configure()")
        dev = self._device
        if self._status() != PDC.STATUS_LIVE:
            self._pdc("PDC_SetStatus", dev, PDC.STATUS_LIVE)
        self._memory, self._dropped = None, []
        self._pdc("PDC_SetRecReady", dev)
        if self._plan.endless:
            self._pdc("PDC_SetEndless", dev)
        status = self._status()
        if status not in (PDC.STATUS_RECREADY, PDC.STATUS_ENDLESS, PDC.STATUS_REC):
            raise InputError(self.name, f"did not become ready to record; it is {status_name(status)}")
        self._armed = True
        if self._settings.mode == "internal":
            self._pdc("PDC_TriggerIn", dev)

    def wait(self, timeout_s: float) -> RecordingStatus:
        if not self._armed or self._plan is None:
            raise OdsplatError(f"{self.name}: wait() before arm()")
        deadline = time.monotonic() + timeout_s
        while True:
            status = self._status()
            if status in ASSUMPTIONS.done_statuses:
                break
            if time.monotonic() >= deadline:
                waiting = " (waiting for the trigger)" if status in (PDC.STATUS_RECREADY, PDC.STATUS_ENDLESS) else ""
                raise CameraTimeout(self.name, f"no complete recording within {timeout_s:g} s; the camera is "
                                               f"{status_name(status)}{waiting}")
            time.sleep(ASSUMPTIONS.poll_s)
        self._armed = False
        dev, child = self._device, self._child
        if status != PDC.STATUS_PLAYBACK:
            self._pdc("PDC_SetStatus", dev, PDC.STATUS_PLAYBACK)
        info = PDC_FRAME_INFO()
        self._pdc("PDC_GetMemFrameInfo", dev, child, ctypes.byref(info))
        width, height = self._pdc.ulongs("PDC_GetMemResolution", dev, child, n=2)
        (rate,) = self._pdc.ulongs("PDC_GetMemRecordRate", dev, child, n=1)
        bit_depth = self._pdc.small("PDC_GetMemBitDepth", dev, child)
        window = select_window(info.m_nStart, info.m_nEnd, info.m_nTrigger, self._plan.pretrigger_frames,
                               self._plan.post_frames)
        self._memory = _Memory(width=width, height=height, record_rate=rate or self._record_rate,
                               bit_depth=bit_depth, window=window)
        log.info("%s: memory holds frames %d..%d, trigger at %d; downloading %d..%d", self.name, info.m_nStart,
                 info.m_nEnd, info.m_nTrigger, window.first_frame, window.last_frame)
        return RecordingStatus(n_frames=window.n_frames, first_counter=window.first_counter,
                               pretrigger_available=window.pretrigger_available)

    def stop(self) -> None:
        if self._device is None:
            return
        if self._status() in (PDC.STATUS_RECREADY, PDC.STATUS_ENDLESS, PDC.STATUS_REC):
            self._pdc("PDC_SetStatus", self._device, ASSUMPTIONS.abort_status)
        self._armed = False

    def close(self) -> None:
        if self._device is None:
            return
        try:
            self.stop()
        finally:
            try:
                self._pdc("PDC_CloseDevice", self._device)
            finally:
                self._device = None

    def __enter__(self) -> PhotronCamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- data logic: the recording -------------------------------------------------------------

    @property
    def dropped(self) -> tuple[int, ...]:
        """Counters PDC_GetMemImageData reported as not captured during the last download."""
        return tuple(self._dropped)

    def frames(self) -> Iterator[Frame]:
        """Downloads the recording frame by frame as it is iterated."""
        if self._memory is None:
            raise OdsplatError(f"{self.name}: no recording to download; arm() and wait() first")
        return self._download(self._memory)

    def _download(self, memory: _Memory) -> Iterator[Frame]:
        bits = self._transfer_bits(memory.bit_depth)
        buffer = (ctypes.c_ubyte * frame_bytes(memory.width, memory.height, bits))()
        warned = False
        for frame_no in range(memory.window.first_frame, memory.window.last_frame + 1):
            counter = frame_no - memory.window.trigger_frame
            try:
                self._pdc("PDC_GetMemImageData", self._device, self._child, frame_no, bits, buffer)
            except PdcError as exc:
                if exc.code != PDC.ERROR_DROP_FRAME:
                    raise
                log.warning("%s: frame %d (counter %d) was not captured", self.name, frame_no, counter)
                self._dropped.append(counter)
                continue
            image = unpack_frame(memoryview(buffer), memory.width, memory.height, bits)
            if bits == 16 and memory.bit_depth < 16 and not warned and int(image.max()) >> memory.bit_depth:
                warned = True
                log.warning("%s: values above %d bits in a %d-bit recording: the SDK may align pixels high; "
                            "see SdkAssumptions.deep_transfer_low_aligned",
                            self.name, memory.bit_depth, memory.bit_depth)
            yield Frame(counter=counter, time_s=counter / memory.record_rate, image=image)
