"""The automatic hammer's protocol byte for byte: the examples, tables and DBC of docs/hammer-protocol.md
against odsplat.acquisition.hammerproto, round trips over serial and CAN, and the refusals."""
from __future__ import annotations

import dataclasses
import re
import struct
import zlib
from pathlib import Path

import can
import numpy as np
import pytest

from odsplat.acquisition import canproto as cp
from odsplat.acquisition import daqproto as dp
from odsplat.acquisition import hammerproto as hp
from odsplat.spine.errors import InputError

pytestmark = pytest.mark.timeout(30)

DOC = Path(__file__).resolve().parents[2] / "docs" / "hammer-protocol.md"

# The messages of the doc's examples; the doc gives their seq and bytes. Floats are exact in f32.
FIRE = hp.Fire(7, hp.LevelMode.FORCE_N, 200.0, 2.0)
SHOT = hp.Shot(7, hp.Outcome.FIRED, 12, 198.5, 0.125)
STATUS = hp.Status(hp.NO_REF, hp.State.DISARMED, True, hp.Fault.NONE, 12, 198.5)
SERIAL_EXAMPLES = {
    "INFO": hp.Info(0, "hammer-1", "2.1", 5.0, 500.0, 2.0),
    "FIRE": FIRE,
    "ACK": hp.Ack(9, hp.MsgType.FIRE),
    "NAK": hp.Nak(9, hp.MsgType.FIRE, hp.NakReason.NOT_ARMED),
    "SHOT": SHOT,
    "STATUS": STATUS,
}
# name -> (message, the seq from_can gives back: a command's own, a reply's RefSeq, 255 for SHOT and unsolicited)
CAN_EXAMPLES = {"FIRE": (FIRE, 9), "ESTOP": (hp.EStop(), 10), "SHOT": (SHOT, 255), "STATUS": (STATUS, 255)}


# ---------------------------------------------------------------------------------- reading the doc

def _chunks() -> list[str]:
    """The doc split at blank lines: paragraphs, tables and (blank-free) code blocks."""
    return [c.strip("\n") for c in DOC.read_text(encoding="utf-8").split("\n\n") if c.strip()]


def _hex(text: str) -> bytes:
    return bytes.fromhex(text.replace(" ", ""))


def _code_after(pattern: str) -> list[tuple[re.Match, list[str], int]]:
    """(match of `pattern` on the paragraph, lines of the code block right after it, chunk index)."""
    chunks = _chunks()
    out = []
    for i, (para, block) in enumerate(zip(chunks, chunks[1:])):
        m = re.match(pattern, para)
        if m and block.startswith("```"):
            out.append((m, block.split("\n")[1:-1], i + 1))
    return out


def _table(header: str) -> list[list[str]]:
    """Rows (cells stripped) of every table whose header row starts with `header`."""
    rows = []
    for chunk in _chunks():
        lines = chunk.split("\n")
        if lines[0].startswith(header) and lines[1].startswith("|---"):
            rows += [[c.strip() for c in line.strip().strip("|").split("|")] for line in lines[2:]]
    return rows


def _table_after(chunk_index: int, header: str) -> list[list[str]]:
    lines = _chunks()[chunk_index + 1].split("\n")
    assert lines[0].startswith(header), lines[0]
    return [[c.strip() for c in line.strip().strip("|").split("|")] for line in lines[2:]]


def _backticked_hex(cell: str) -> bytes:
    return b"".join(_hex(h) for h in re.findall(r"`([0-9a-f ]+)`", cell))


def _serial_examples() -> dict[str, tuple[int, dict[str, bytes], int]]:
    found = {}
    for m, lines, idx in _code_after(r"([A-Z_]+), (host|hammer) seq (\d+):"):
        name, direction, seq = m.group(1), m.group(2), int(m.group(3))
        assert name not in found, f"two serial examples of {name}"
        assert (direction == "host") == isinstance(SERIAL_EXAMPLES[name], hp.COMMANDS), name
        found[name] = (seq, {k: _hex(v) for k, v in (re.match(r"(\w+):\s+([0-9a-f ]+)$", ln).groups() for ln in lines)},
                       idx)
    return found


def _can_examples() -> dict[str, tuple[int | None, int, bytes, int]]:
    found = {}
    for m, lines, idx in _code_after(r"([A-Z_]+) on CAN(?:, Seq (\d+))?:"):
        (line,) = lines
        frame_id, data = re.match(r"id 0x([0-9a-f]{3})\s+data ([0-9a-f ]+)$", line).groups()
        found[m.group(1)] = (None if m.group(2) is None else int(m.group(2)), int(frame_id, 16), _hex(data), idx)
    return found


# ---------------------------------------------------------------------------------- the examples

def test_serial_examples_are_byte_exact():
    found = _serial_examples()
    assert set(found) == set(SERIAL_EXAMPLES)
    for name, (seq, lines, _) in found.items():
        message = SERIAL_EXAMPLES[name]
        assert set(lines) == {"packet", "frame"}, name
        assert lines["packet"] == dp.encode_packet(message, seq), name
        assert lines["frame"] == hp.encode_frame(message, seq), name
        assert zlib.crc32(lines["packet"][:-4]).to_bytes(4, "little") == lines["packet"][-4:]
        dec = hp.frame_decoder("doc")
        assert dec.feed(lines["frame"]) == [dp.Packet(seq, message)], name
        assert dec.stats.packets == 1 and dec.stats.malformed == 0


def test_fire_field_table_spells_out_the_packet():
    seq, lines, idx = _serial_examples()["FIRE"]
    rows = _table_after(idx, "| packet bytes | field |")
    assert b"".join(_backticked_hex(r[0]) for r in rows) == lines["packet"]
    assert dict((r[1].split()[0], r[1]) for r in rows)["level"] == "level 200.0 (f32)"
    assert struct.unpack("<f", _backticked_hex(rows[5][0]))[0] == FIRE.level


def test_can_examples_are_byte_exact():
    found = _can_examples()
    assert set(found) == set(CAN_EXAMPLES)
    for name, (doc_seq, frame_id, data, _) in found.items():
        message, seq_back = CAN_EXAMPLES[name]
        if isinstance(message, hp.COMMANDS):
            assert doc_seq == seq_back, name  # the paragraph states the command's Seq
        frame = hp.to_can(message, seq_back)
        assert (frame.arbitration_id, bytes(frame.data), frame.is_extended_id) == (frame_id, data, False), name
        assert hp.from_can(frame) == (seq_back, message), name
    _, _, data, idx = found["FIRE"]
    rows = _table_after(idx, "| bytes | signals |")
    assert b"".join(_backticked_hex(r[0]) for r in rows) == data


# ---------------------------------------------------------------------------------- tables vs code

_FIELD_FMT = {"u8": "B", "u16": "H", "u32": "I", "f32": "f"}


def _decode_by_doc(layout: str, body: bytes) -> dict[str, object]:
    """A body decoded by the doc's layout (`name type`, ...) alone."""
    out, pos = {}, 0
    for field in layout.replace("`", "").split(","):
        name, kind = field.split()
        if kind == "str8":
            n = body[pos]
            out[name] = body[pos + 1:pos + 1 + n].decode("ascii")
            pos += 1 + n
        else:
            (out[name],) = struct.unpack_from("<" + _FIELD_FMT[kind], body, pos)
            pos += struct.calcsize(_FIELD_FMT[kind])
    assert pos == len(body), f"{layout}: {len(body) - pos} bytes left"
    return out


BODY_SAMPLES = [hp.Hello(), hp.Arm(), hp.Disarm(), hp.Fire(513, hp.LevelMode.ENERGY_J, 0.75, 65.535), hp.EStop(),
                hp.Reset(), hp.GetStatus(), hp.Info(258, "sim hammer", "v1.4", 2.5, 1000.0, 3.25),
                hp.Ack(65000, hp.MsgType.ARM), hp.Nak(3, hp.MsgType.RESET, hp.NakReason.FAULTED, "still stuck"),
                hp.Shot(40000, hp.Outcome.EXPIRED, 70000, 0.0, 2.0, hp.ShotFlag.REBOUND),
                hp.Status(12, hp.State.FAULT, False, hp.Fault.STUCK, 70000, 0.5)]


def test_message_tables_match_the_codec():
    rows = _table("| type | name | body |")
    assert {int(r[0].strip("`"), 16): r[1] for r in rows} == {int(t): t.name for t in hp.MsgType}
    layouts = {r[1]: r[2] for r in rows}
    assert {type(m) for m in BODY_SAMPLES} == set(hp.MESSAGES.values())
    for message in BODY_SAMPLES:
        layout = layouts[message.TYPE.name]
        got = {} if layout == "(empty)" else _decode_by_doc(layout, message._body())
        want = {}
        for f in dataclasses.fields(message):
            value = getattr(message, f.name)
            want[f.name] = int(value) if isinstance(value, (bool, int)) else value
        if "timeout_ms" in got:
            got["timeout_s"] = got.pop("timeout_ms") / 1000
        assert got == want, message.TYPE.name


@pytest.mark.parametrize("header, enum", [
    ("| NAK reason | code |", hp.NakReason), ("| state | code |", hp.State), ("| fault | code |", hp.Fault),
    ("| outcome | code |", hp.Outcome), ("| mode | code |", hp.LevelMode), ("| shot flag | bit |", hp.ShotFlag),
])
def test_code_tables_match_the_enums(header, enum):
    assert {r[0]: int(r[1].strip("`"), 0) for r in _table(header)} == {e.name: int(e) for e in enum}


def test_dbc_frames_and_signals_are_the_documented_ones():
    db = hp.load_dbc()
    frames = {r[0].strip("`"): r for r in _table("| frame | id | bytes | direction |")}
    assert set(frames) == {m.name for m in db.messages}
    assert [int(frames[m.name][1].strip("`"), 16) for m in db.messages] == [m.frame_id for m in db.messages]
    assert sorted(m.frame_id for m in db.messages) == sorted(hp.CAN_IDS)
    for msg in db.messages:
        _, _, n_bytes, direction, _ = frames[msg.name]
        assert int(n_bytes) == msg.length
        assert msg.senders == [direction.split(" → ")[0].upper()]
    headings = {}
    for chunk_index, chunk in enumerate(_chunks()):
        m = re.match(r"### (HAMMER_\w+) \(`0x([0-9a-f]{3})`, (\d) bytes?\)$", chunk)
        if m:
            rows = _table_after(chunk_index, "| signal | bits |")
            headings[m.group(1)] = (int(m.group(2), 16), int(m.group(3)), rows)
    assert set(headings) == set(frames)
    for name, (frame_id, n_bytes, rows) in headings.items():
        msg = db.get_message_by_name(name)
        assert (frame_id, n_bytes) == (msg.frame_id, msg.length)
        documented = {}
        for sig_name, bits, scale, unit, _ in rows:
            lo, _, hi = bits.partition("-")
            documented[sig_name.strip("`")] = (int(lo), int(hi or lo) - int(lo) + 1, float(scale),
                                               None if unit == "–" else unit)
        assert documented == {s.name: (s.start, s.length, float(s.scale), s.unit or None) for s in msg.signals}, name
        assert all(s.byte_order == "little_endian" and not s.is_signed and s.offset == 0 for s in msg.signals)


def test_dbc_value_tables_are_the_enums():
    db = hp.load_dbc()

    def choices(frame_id, signal):
        sig = db.get_message_by_frame_id(frame_id).get_signal_by_name(signal)
        return {int(k): str(v) for k, v in sig.choices.items()}

    assert choices(hp.CMD_ID, "Command") == {int(c.TYPE) - 0x10: c.TYPE.name for c in hp.COMMANDS}
    assert choices(hp.CMD_ID, "Mode") == {int(e): e.name for e in hp.LevelMode}
    assert choices(hp.REPLY_ID, "NakReason") == {0: "NONE", **{int(e): e.name for e in hp.NakReason}}
    assert choices(hp.STATUS_ID, "State") == {int(e): e.name for e in hp.State}
    assert choices(hp.STATUS_ID, "Fault") == {int(e): e.name for e in hp.Fault}
    assert choices(hp.SHOT_ID, "Outcome") == {int(e): e.name for e in hp.Outcome}


# ---------------------------------------------------------------------------------- round trips

@pytest.mark.parametrize("message", BODY_SAMPLES, ids=lambda m: m.TYPE.name)
def test_serial_round_trip(message):
    dec = hp.frame_decoder("test")
    assert dec.feed(hp.encode_frame(message, 65535)) == [dp.Packet(65535, message)]


# Messages that fit CAN exactly: 8-bit ids and seqs, 16-bit counts, values on the DBC's grid.
CAN_ROUND_TRIP = [
    (hp.Hello(), 0), (hp.Arm(), 1), (hp.Disarm(), 2), (hp.Fire(255, hp.LevelMode.ENERGY_J, 1.25, 65.535), 3),
    (hp.Fire(0, hp.LevelMode.FORCE_N, 16777.215, 0.001), 4), (hp.EStop(), 255), (hp.Reset(), 6), (hp.GetStatus(), 7),
    (hp.Info(8, "", "2.1", 5.0, 500.0, 2.5), 8), (hp.Ack(9, hp.MsgType.ESTOP), 9),
    (hp.Nak(10, hp.MsgType.FIRE, hp.NakReason.BAD_LEVEL), 10), (hp.Shot(7, hp.Outcome.FAULT, 65535, 0.0, 0.4095), 255),
    (hp.Shot(8, hp.Outcome.FIRED, 3, 1234.567, 0.0012, hp.ShotFlag.REBOUND), 255),
    (hp.Status(11, hp.State.ESTOP, False, hp.Fault.OVERTEMP, 0, 6553.5), 11),
    (hp.Status(hp.NO_REF, hp.State.FIRING, True, hp.Fault.NONE, 4, 0.1), 255),
]


@pytest.mark.parametrize("message, seq", CAN_ROUND_TRIP, ids=[f"{m.TYPE.name}-{s}" for m, s in CAN_ROUND_TRIP])
def test_can_round_trip(message, seq):
    frame = hp.to_can(message, seq)
    assert frame.arbitration_id in hp.CAN_IDS and not frame.is_extended_id
    assert len(frame.data) == hp.load_dbc().get_message_by_frame_id(frame.arbitration_id).length
    assert hp.from_can(frame) == (seq, message)


def test_can_covers_every_message_type():
    assert {type(m) for m, _ in CAN_ROUND_TRIP} == set(hp.MESSAGES.values())


def test_can_narrows_as_documented():
    fire = hp.Fire(300, hp.LevelMode.FORCE_N, 12.3456, 1.0)
    assert hp.from_can(hp.to_can(fire, 300)) == (44, hp.Fire(44, hp.LevelMode.FORCE_N, 12.346, 1.0))  # mod 256
    shot = hp.Shot(300, hp.Outcome.EXPIRED, 70000, 0.0, 2.0, hp.ShotFlag.REBOUND)
    assert hp.from_can(hp.to_can(shot))[1] == hp.Shot(44, hp.Outcome.EXPIRED, 4464, 0.0, 0.4095, hp.ShotFlag.REBOUND)
    info = hp.Info(3, "hammer-1", "v2.10.3", 5.4, 499.6, 2.0)
    assert hp.from_can(hp.to_can(info))[1] == hp.Info(3, "", "2.10", 6.0, 499.0, 2.0)  # no id, whole N inwards
    assert hp.from_can(hp.to_can(hp.Nak(4, hp.MsgType.ARM, hp.NakReason.ESTOPPED, "RESET first")))[1] == \
        hp.Nak(4, hp.MsgType.ARM, hp.NakReason.ESTOPPED)  # no text
    status = hp.Status(hp.NO_REF, hp.State.ARMED, True, hp.Fault.NONE, 65537, 198.54)
    assert bytes(hp.to_can(status).data)[0] == 255
    assert hp.from_can(hp.to_can(status)) == (255, hp.Status(hp.NO_REF, hp.State.ARMED, True, hp.Fault.NONE, 1, 198.5))
    assert hp.to_can(hp.EStop(), 10).arbitration_id == hp.ESTOP_ID
    cmd_estop = can.Message(arbitration_id=hp.CMD_ID, is_extended_id=False, data=bytes([5, 12, 0, 0, 0, 0, 0, 0]))
    assert hp.from_can(cmd_estop) == (12, hp.EStop())  # Command 5 on HAMMER_CMD also means ESTOP


# ---------------------------------------------------------------------------------- bad input

def _raw(version: int, type_: int, body: bytes, seq: int = 5) -> dp.RawPacket:
    head = bytes([version, type_]) + seq.to_bytes(2, "little") + body
    return dp.check_packet(head + zlib.crc32(head).to_bytes(4, "little"))


def test_corrupted_byte_is_a_crc_error_and_skipped():
    messages = [hp.GetStatus(), FIRE, hp.Arm(), hp.EStop(), SHOT, STATUS]
    frames = [hp.encode_frame(m, k) for k, m in enumerate(messages)]
    packet = bytearray(dp.encode_packet(FIRE, 1))
    packet[8] ^= 0x04  # in the level: COBS still decodes, the CRC does not match
    frames[1] = dp.frame(bytes(packet))
    stream = b"".join(frames)
    dec = hp.frame_decoder("test")
    got = []
    for k in range(0, len(stream), 5):  # partial frames too
        got += dec.feed(stream[k:k + 5])
    assert got == [dp.Packet(k, m) for k, m in enumerate(messages) if k != 1]
    assert (dec.stats.crc_errors, dec.stats.cobs_errors, dec.stats.malformed, dec.stats.packets) == (1, 0, 0, 5)


@pytest.mark.parametrize("type_", [0x18, 0x92, 0x01, 0x85], ids=hex)  # gaps in the hammer's codes; DAQ types
def test_unknown_type_is_refused_unknown_type(type_):
    with pytest.raises(hp.HammerProtocolError, match=f"unknown message type 0x{type_:02x}") as e:
        hp.parse_packet(_raw(1, type_, b""))
    assert e.value.reason == hp.NakReason.UNKNOWN_TYPE
    dec = hp.frame_decoder("test")
    assert dec.feed(dp.frame(dp.encode_packet(dp.Hello(), 0))) == [] and dec.stats.malformed == 1


def test_bad_version_and_fire_bodies_are_refused():
    with pytest.raises(hp.HammerProtocolError) as e:
        hp.parse_packet(_raw(2, hp.MsgType.HELLO, b""))
    assert e.value.reason == hp.NakReason.UNSUPPORTED_VERSION
    body = FIRE._body()
    assert len(body) == 11
    for bad in (body[:-1], body + b"\x00", b""):
        with pytest.raises(hp.HammerProtocolError, match="malformed FIRE") as e:
            hp.parse_packet(_raw(1, hp.MsgType.FIRE, bad))
        assert e.value.reason == hp.NakReason.MALFORMED
    # An unknown mode parses: refusing it (BAD_LEVEL) is the hammer's job.
    assert hp.parse_packet(_raw(1, hp.MsgType.FIRE, body[:2] + b"\x07" + body[3:])).message.mode == 7


@pytest.mark.parametrize("fire, problem", [
    (hp.Fire(1, hp.LevelMode.FORCE_N, 16777.216, 1.0), "level"),
    (hp.Fire(1, hp.LevelMode.FORCE_N, -1.0, 1.0), "level"),
    (hp.Fire(1, hp.LevelMode.FORCE_N, float("nan"), 1.0), "level"),
    (hp.Fire(1, hp.LevelMode.FORCE_N, 100.0, 65.536), "timeout"),
    (hp.Fire(1, hp.LevelMode.FORCE_N, 100.0, 0.0), "timeout"),
])
def test_can_fire_outside_the_frame_is_refused(fire, problem):
    with pytest.raises(InputError, match=f"^FIRE: {problem}"):
        hp.to_can(fire, 1)


def test_serial_fire_timeout_outside_range_is_refused():
    with pytest.raises(InputError, match="^FIRE: timeout"):
        hp.encode_frame(hp.Fire(1, hp.LevelMode.FORCE_N, 100.0, 65.536), 0)


def test_other_devices_frames_are_not_the_hammers():
    counts = np.array([[1, -2, 3]], dtype=np.int16)
    frames = [cp.acc_data_frames(1, 0, counts)[0], cp.command_frame(1, cp.Command.START, 2, 3),
              cp.command_frame(cp.BROADCAST, cp.Command.STOP), cp.error_frame(),
              can.Message(arbitration_id=hp.CMD_ID, is_extended_id=True, data=hp.to_can(FIRE, 9).data)]
    assert frames[0].arbitration_id == 0x101
    assert [hp.from_can(f) for f in frames] == [None] * len(frames)


def test_short_can_frame_is_malformed():
    with pytest.raises(hp.HammerProtocolError, match="CAN id 0x300") as e:
        hp.from_can(can.Message(arbitration_id=hp.CMD_ID, is_extended_id=False, data=bytes(3)))
    assert e.value.reason == hp.NakReason.MALFORMED


def test_unknown_can_command_is_unknown_type():
    with pytest.raises(hp.HammerProtocolError) as e:
        hp.from_can(can.Message(arbitration_id=hp.CMD_ID, is_extended_id=False, data=bytes([9, 1, 0, 0, 0, 0, 0, 0])))
    assert e.value.reason == hp.NakReason.UNKNOWN_TYPE


def test_any_frame_on_the_estop_id_stops():
    for frame in (can.Message(arbitration_id=hp.ESTOP_ID, is_extended_id=False, data=b""),
                  can.Message(arbitration_id=hp.ESTOP_ID, is_extended_id=False, is_remote_frame=True, dlc=1),
                  can.Message(arbitration_id=hp.ESTOP_ID, is_extended_id=False, data=bytes([7, 1, 2]))):
        assert hp.from_can(frame)[1] == hp.EStop()


def test_nak_of_an_unknown_command_encodes_on_can():
    nak = hp.Nak(3, 0x18, hp.NakReason.UNKNOWN_TYPE)
    assert hp.from_can(hp.to_can(nak))[1] == nak
    assert hp.from_can(hp.to_can(hp.Nak(3, 0x42, 200)))[1] == hp.Nak(3, 0x10, 200)  # not a command code: RefCommand 0


def test_fire_timeout_below_a_millisecond_is_refused():
    with pytest.raises(InputError):
        hp.encode_frame(hp.Fire(1, hp.LevelMode.FORCE_N, 10.0, 0.0004), 1)
    with pytest.raises(InputError):
        hp.to_can(hp.Fire(1, hp.LevelMode.FORCE_N, 10.0, 0.0004), 1)
