"""The DAQ wire protocol byte for byte, and the simulated DAQ over a real PTY: sines to 1 LSB and every fault."""
from __future__ import annotations

import logging
import time
import zlib
from pathlib import Path

import numpy as np
import pytest
import serial

from odsplat.acquisition import daqproto as dp
from odsplat.hil_sim.daq import CLOCK_HZ, DAQFaults, SimDAQDevice, SineSource, register_source, register_url_handler
from odsplat.spine.errors import InputError
from tests.hil_sim.daqhost import DAQHost as _Host
from tests.hil_sim.daqhost import channels as _channels
from tests.hil_sim.daqhost import open_port as _open

log = logging.getLogger(__name__)
pytestmark = pytest.mark.timeout(30)

# The examples printed in docs/daq-protocol.md.
DOC_CONFIGURE = dp.Configure(25600, (dp.ChannelConfig(0, 10.0, "force"), dp.ChannelConfig(3, 5.0, "acc1")))
DOC_CONFIGURE_FRAME = ("04 01 02 01 01 02 64 01 02 02 01 01 0a 20 41 05 66 6f 72 63 65 03 01 0c a0 40 04 61 63 63 31"
                       " 24 f1 e4 46 00")
DOC_DATA = dp.Data(256, np.array([[0, 32767], [-1, -32767]], dtype=np.int16))
DOC_DATA_PACKET = "01 85 07 00 00 01 00 00 00 00 00 00 02 00 00 00 ff ff ff 7f 01 80 f6 85 2d 39"
DOC_DATA_FRAME = "04 01 85 07 01 02 01 01 01 01 01 01 02 02 01 01 0b ff ff ff 7f 01 80 f6 85 2d 39 00"


@pytest.fixture(autouse=True, scope="module")
def _handler():
    register_url_handler()


# ---------------------------------------------------------------------------------- COBS, packets

@pytest.mark.parametrize("raw, encoded", [
    ("", "01"), ("00", "01 01"), ("00 00", "01 01 01"), ("00 11 00", "01 02 11 01"),
    ("11 22 00 33", "03 11 22 02 33"), ("11 22 33 44", "05 11 22 33 44"), ("11 00 00 00", "02 11 01 01 01"),
])
def test_cobs_known_vectors(raw, encoded):
    assert dp.cobs_encode(bytes.fromhex(raw)) == bytes.fromhex(encoded)
    assert dp.cobs_decode(bytes.fromhex(encoded)) == bytes.fromhex(raw)


def test_cobs_long_runs_and_round_trips():
    run254 = bytes(range(1, 255))
    assert dp.cobs_encode(run254) == b"\xff" + run254  # no trailing code byte after a final full block
    assert dp.cobs_encode(b"\x00" + run254) == b"\x01\xff" + run254
    assert dp.cobs_encode(run254 + b"\xff") == b"\xff" + run254 + b"\x02\xff"
    assert dp.cobs_encode(run254 + b"\x00") == b"\xff" + run254 + b"\x01\x01"
    rng = np.random.default_rng(1)
    cases = [bytes(n) for n in (1, 253, 254, 255, 600)] + [b"\x07" * n for n in (253, 254, 255, 508, 509, 1000)]
    cases += [rng.integers(0, 256, n, dtype=np.uint8).tobytes() for n in range(0, 800, 37)]
    cases += [rng.choice([0, 1, 255], n).astype(np.uint8).tobytes() for n in (300, 3000)]
    cases.append(rng.integers(1, 256, dp.MAX_PACKET_BYTES, dtype=np.uint8).tobytes())  # worst-case overhead
    for data in cases:
        enc = dp.cobs_encode(data)
        assert 0 not in enc and len(enc) <= len(data) + len(data) // 254 + 1
        assert dp.cobs_decode(enc) == data
    assert len(dp.cobs_encode(cases[-1])) + 1 <= dp.MAX_FRAME_BYTES + 1
    for bad in (b"\x00", b"\x05\x01", b"\x03\x01\x00"):
        with pytest.raises(ValueError):
            dp.cobs_decode(bad)


def test_documented_examples_are_byte_exact():
    assert zlib.crc32(b"123456789") == 0xCBF43926  # the CRC-32 named in the spec
    assert dp.encode_frame(DOC_CONFIGURE, 1) == bytes.fromhex(DOC_CONFIGURE_FRAME)
    assert dp.encode_packet(DOC_DATA, 7) == bytes.fromhex(DOC_DATA_PACKET)
    assert dp.encode_frame(DOC_DATA, 7) == bytes.fromhex(DOC_DATA_FRAME)
    doc = (Path(__file__).resolve().parents[2] / "docs" / "daq-protocol.md").read_text()
    assert all(h in doc for h in (DOC_CONFIGURE_FRAME, DOC_DATA_PACKET, DOC_DATA_FRAME))  # the spec shows these bytes
    (packet,) = dp.FrameDecoder().feed(bytes.fromhex(DOC_DATA_FRAME))
    assert packet.seq == 7 and packet.message.first_sample == 256
    np.testing.assert_array_equal(packet.message.counts, [[0, 32767], [-1, -32767]])


MESSAGES = [
    dp.Hello(), DOC_CONFIGURE, dp.Start(), dp.Stop(),
    dp.Info(3, "odsplat-simdaq", "sim-1.0", 8, 102400.0, (1.0, 10.0)),
    dp.ConfigAck(1, 9997.864225781846, DOC_CONFIGURE.channels),
    dp.Ack(2, dp.MsgType.START), dp.Nak(4, dp.MsgType.CONFIGURE, dp.NakReason.BAD_RANGE, "+-3 V"),
    dp.Status(dp.StatusFlag.CLIPPED | dp.StatusFlag.RUNNING, 0b101, 2**40 + 3),
]


@pytest.mark.parametrize("message", MESSAGES, ids=lambda m: m.TYPE.name)
def test_message_round_trip(message):
    (packet,) = dp.FrameDecoder().feed(dp.encode_frame(message, 65535))
    assert packet == dp.Packet(65535, message)


def test_data_round_trip_max_size():
    n_ch = 8
    n = (dp.MAX_PACKET_BYTES - 18) // (2 * n_ch)
    counts = np.random.default_rng(2).integers(-32767, 32768, (n_ch, n)).astype(np.int16)
    counts[:, :300] = 0  # long zero runs
    wire = dp.encode_packet(dp.Data(2**63 + 5, counts), 9)
    assert n == 510 and len(wire) == 18 + 2 * n_ch * n <= dp.MAX_PACKET_BYTES < len(wire) + 2 * n_ch
    (packet,) = dp.FrameDecoder().feed(dp.frame(wire))
    assert packet.message.first_sample == 2**63 + 5
    np.testing.assert_array_equal(packet.message.counts, counts)
    with pytest.raises(InputError):
        dp.encode_packet(dp.Data(0, np.zeros((n_ch, n + 1), np.int16)), 0)


def test_decoder_survives_garbage_and_split_feeds():
    frames = [dp.encode_frame(dp.Status(dp.StatusFlag(0), 0, k), k) for k in range(50)]
    corrupt = bytearray(dp.encode_packet(dp.Status(dp.StatusFlag(0), 0, 10), 10))
    corrupt[5] ^= 0x10  # a bit error under the framing: COBS is intact, the CRC is not
    frames[10] = dp.frame(bytes(corrupt))
    frames[20] = b"\xff\x03\x00"  # COBS code running past the end of the frame
    frames[30] = b"\x55" * (dp.MAX_FRAME_BYTES + 10) + frames[30]  # line noise longer than any frame
    frames[40] = frames[40][:5] + b"\x00"  # truncated: too short to be a packet
    stream = b"\x00\x00garbage\x00" + b"".join(frames)
    dec = dp.FrameDecoder("test")
    packets = []
    for k in range(0, len(stream), 7):  # partial frames everywhere
        packets += dec.feed(stream[k:k + 7])
    assert [p.seq for p in packets] == [k for k in range(50) if k not in (10, 20, 30, 40)]
    assert (dec.stats.crc_errors, dec.stats.cobs_errors, dec.stats.oversize) == (1, 3, 1)  # 10; garbage, 20, 40; 30
    # A CRC-valid packet of an unknown type or version is malformed, not a crash.
    bad = dp.frame(_with_crc(b"\x01\x99\x00\x00")) + dp.frame(_with_crc(b"\x02\x01\x00\x00"))
    assert dec.feed(bad) == [] and dec.stats.malformed == 2


def _with_crc(head: bytes) -> bytes:
    return head + zlib.crc32(head).to_bytes(4, "little")


def test_stream_checker_reports_exact_gaps():
    def data(seq, first, n=10):
        return dp.Packet(seq, dp.Data(first, np.zeros((2, n), np.int16)))

    chk = dp.DataStreamChecker(2, device="t", next_seq=65534)
    events = []
    for p in [data(65534, 0), data(65535, 10), data(1, 30),  # seq wraps; seq 0 (samples 20..29) lost
              dp.Packet(2, dp.Status(dp.StatusFlag.RUNNING, 0, 40)), data(3, 40),
              data(4, 55),  # device skipped 50..54 itself (overrun): no packet missing
              dp.Packet(6, dp.Status(dp.StatusFlag.RUNNING, 0, 60)), data(7, 65),  # lost seq 5 held no samples
              dp.Packet(9, dp.Ack(9, dp.MsgType.STOP))]:  # seq 8 lost: the tail DATA
        events += chk.feed(p)
    events += chk.finish(80)  # final STATUS: the device acquired 80, samples 75..79 never came
    gaps = [e for e in events if isinstance(e, dp.SampleGap)]
    assert gaps == [dp.SampleGap(20, 10, 1), dp.SampleGap(50, 5, 0), dp.SampleGap(75, 5, 1)]
    assert (chk.stats.samples, chk.stats.lost_samples, chk.stats.lost_packets) == (60, 20, 3)
    with pytest.raises(dp.DAQProtocolError, match="went back"):
        chk.feed(data(10, 70))
    with pytest.raises(dp.DAQProtocolError, match="3 channels"):
        chk.feed(dp.Packet(11, dp.Data(90, np.zeros((3, 1), np.int16))))


def test_verify_config_names_device_and_mismatch():
    ack = dp.ConfigAck(1, 25600.0, (dp.ChannelConfig(0, 10.0, "force"), dp.ChannelConfig(3, 10.0, "acc1")))
    with pytest.raises(dp.DAQProtocolError, match=r"^daq7: configuration mismatch.*range_v=5\.0"):
        dp.verify_config(DOC_CONFIGURE, ack, device="daq7")
    dp.verify_config(DOC_CONFIGURE, dp.ConfigAck(1, 25600.0, DOC_CONFIGURE.channels), device="daq7")


LSB_V = 10.0 / dp.FULL_SCALE_COUNTS


def test_eight_sines_over_pty_within_one_lsb():
    n = 200_000
    with _open("simdaq://sine?fs=25600&channels=8") as port:
        take = _Host(port).take(_channels(8), 25600, n)
    assert take.info.n_inputs == 8 and take.info.device_id == "odsplat-simdaq"
    assert take.ack.sample_rate_hz == 25600.0
    assert take.gaps == [] and take.checker.stats.lost_packets == 0
    assert take.final.sample_counter == take.checker.next_sample >= n
    assert take.final.flags == 0  # no clipping, no overrun, stopped
    got = take.volts(n)
    truth = SineSource.default(8).volts(0, n, 25600.0)
    assert np.max(np.abs(got - truth)) <= 0.5 * LSB_V + 1e-12  # rounding to the nearest count
    rate = n / take.elapsed_s  # not asserted: bench/daq.py measures the rate against its baselines
    log.info("PTY throughput: %.0f samples/s x 8 channels (%.1f MB/s of samples)", rate, rate * 16 / 1e6)


def test_actual_rate_and_refusals():
    with _open("simdaq://sine?fs=51200&channels=4&range=1,10") as port:
        host = _Host(port, timeout_s=5)
        assert host.request(dp.Hello()).message.ranges_v == (1.0, 10.0)
        ack = host.request(dp.Configure(10000, tuple(_channels(2, 1.0)))).message
        assert ack.sample_rate_hz == pytest.approx(CLOCK_HZ / 1311) == pytest.approx(9997.8642)  # not 10000
        for message, reason in [
            (dp.Configure(60000, tuple(_channels(2))), "BAD_RATE"),
            (dp.Configure(25600, (dp.ChannelConfig(0, 3.0, "a"),)), "BAD_RANGE"),
            (dp.Configure(25600, (dp.ChannelConfig(4, 10.0, "a"),)), "BAD_CHANNEL"),
            (dp.Configure(25600, (dp.ChannelConfig(1, 10.0, "a"), dp.ChannelConfig(1, 10.0, "b"))), "BAD_CHANNEL"),
        ]:
            with pytest.raises(dp.DAQProtocolError, match=f"simdaq://sine.*refused CONFIGURE: {reason}"):
                host.request(message)
    with _open("simdaq://sine") as port:
        with pytest.raises(dp.DAQProtocolError, match="refused START: NOT_CONFIGURED"):
            _Host(port, timeout_s=5).request(dp.Start())


def test_dropped_packets_are_exact_gaps():
    # 64-sample blocks: DATA packet i holds samples 64 i .. 64 i + 63
    with _open("simdaq://sine?channels=2&block=64&drop_every=10&drop=0,3") as port:
        take = _Host(port).take(_channels(2), 25600, 5000)
    lost = sorted({0, 3} | set(range(9, 10**4, 10)))
    lost = [i for i in lost if 64 * i < take.final.sample_counter]
    assert [(g.first_sample, g.n_samples) for g in take.gaps] == [(64 * i, 64) for i in lost]
    assert all(g.lost_packets == 1 for g in take.gaps)
    assert take.checker.stats.lost_samples == 64 * len(lost)
    assert take.checker.stats.samples + take.checker.stats.lost_samples == take.final.sample_counter
    got, truth = take.volts(5000), SineSource.default(2).volts(0, 5000, 25600.0)
    holes = np.isnan(got[0])
    assert holes.sum() == sum(64 for i in lost if 64 * i < 5000)  # gaps stay holes, never filled
    assert np.max(np.abs(got[:, ~holes] - truth[:, ~holes])) <= 0.5 * LSB_V + 1e-12


def test_bit_errors_are_crc_failures_and_gaps():
    with _open("simdaq://sine?channels=3&block=100&bit_error_every=7&seed=3") as port:
        take = _Host(port).take(_channels(3), 25600, 7000)
    n_packets = -(-take.final.sample_counter // 100)
    corrupted = [i for i in range(n_packets) if (i + 1) % 7 == 0]
    assert take.decoder.stats.crc_errors == len(corrupted) and take.decoder.stats.cobs_errors == 0
    assert [(g.first_sample, g.n_samples, g.lost_packets) for g in take.gaps] == [(100 * i, 100, 1) for i in corrupted]
    assert take.checker.stats.samples == take.final.sample_counter - 100 * len(corrupted)


def test_clipping_saturates_and_is_flagged():
    # Channel 1 swings +-12 V into the +-10 V range; channel 0 stays inside.
    register_source("clipper", SineSource((5.0, 12.0), (50.0, 80.0), (0.0, 0.0)))
    with _open("simdaq://clipper") as port:
        take = _Host(port).take(_channels(2), 25600, 3000)
    assert take.statuses[0].flags == dp.StatusFlag.CLIPPED | dp.StatusFlag.RUNNING  # raised while running
    assert take.final.flags == dp.StatusFlag.CLIPPED and take.final.clipped_channels == 0b10
    counts = np.concatenate([b.counts for b in take.blocks], axis=1)
    truth = np.rint(SineSource((5.0, 12.0), (50.0, 80.0), (0.0, 0.0)).volts(0, counts.shape[1], 25600.0)
                    * (32767 / 10.0))
    over = np.abs(truth[1]) > 32767
    assert over.sum() > 100
    np.testing.assert_array_equal(counts[1, over], np.sign(truth[1, over]) * 32767)
    np.testing.assert_array_equal(counts[:, ~over], truth[:, ~over])
    assert counts.min() == -32767  # -32768 is never sent


def test_disconnect_mid_take_names_the_port():
    with _open("simdaq://sine?channels=8&disconnect_after=20000") as port:
        host = _Host(port, timeout_s=25)
        # The port's error, not the host's TimeoutError: the disconnect is seen, not waited out.
        with pytest.raises(serial.SerialException, match=r"^simdaq://sine\?channels=8&disconnect_after=20000: "
                                                         r"device disconnected after 20000 samples"):
            host.take(_channels(8), 25600, 10**9)
        assert host.decoder.stats.packets > 0


def test_clock_drift_shifts_the_apparent_frequency():
    ppm = 150.0
    n = 200_000
    with _open(f"simdaq://sine?channels=1&block=1000&drift_ppm={ppm}") as port:
        take = _Host(port).take(_channels(1), 25600, n)
    assert take.ack.sample_rate_hz == 25600.0  # the device does not know its clock drifts
    x = take.volts(n)[0]
    true_rate = 25600.0 * (1 + ppm * 1e-6)
    assert np.max(np.abs(x - SineSource.default(1).volts(0, n, true_rate)[0])) <= 0.5 * LSB_V + 1e-12
    # Demodulate at the nominal 117 Hz; the phase slope is the frequency error seen on the nominal time base.
    t = np.arange(n) / 25600.0
    z = (x * np.exp(-2j * np.pi * 117.0 * t)).reshape(-1, 1000).mean(axis=1)
    phase = np.unwrap(np.angle(z))
    df_hz = np.polyfit(t.reshape(-1, 1000).mean(axis=1), phase, 1)[0] / (2 * np.pi)
    measured_ppm = (117.0 / (117.0 + df_hz) - 1) * 1e6
    assert measured_ppm == pytest.approx(ppm, abs=1.0)


def test_realtime_paces_and_reports_overrun():
    t0 = time.monotonic()  # before the device exists: its clock cannot have started earlier
    with _open("simdaq://sine?channels=1&fs=25600&realtime=1&block=256") as port:
        take = _Host(port).take(_channels(1), 25600, 12_800)
    assert time.monotonic() - t0 > 0.45  # 0.5 s of samples at 25.6 kHz: never faster than real time
    assert take.gaps == []
    # A host that stalls for 1 s: the device discards what it cannot queue and says so.
    with _open("simdaq://sine?channels=1&fs=25600&realtime=1&block=256") as port:
        take = _Host(port).take(_channels(1), 25600, 40_000, pause_s=1.2)
    assert take.final.flags & dp.StatusFlag.OVERRUN
    assert take.gaps and all(g.lost_packets == 0 for g in take.gaps)
    assert take.checker.stats.samples + take.checker.stats.lost_samples == take.final.sample_counter


def test_device_object_without_url():
    device = SimDAQDevice(SineSource.default(2), faults=DAQFaults())
    try:
        path = device.serve_pty()
        with serial.Serial(path, timeout=0.5) as port:
            take = _Host(port).take(_channels(2), 25600, 1000)
        assert take.final.sample_counter >= 1000 and take.gaps == []
    finally:
        device.close()


@pytest.mark.parametrize("url, problem", [
    ("simdaq://nosuch", "no source 'nosuch'"),
    ("simdaq://sine?block=many", "option block='many'"),
    ("simdaq://sine?colour=red", "bad source options"),
    ("simdaq://clipper?channels=2", "unknown URL options"),
])
def test_bad_urls_name_the_url(url, problem):
    register_source("clipper", SineSource((5.0, 12.0), (50.0, 80.0), (0.0, 0.0)))
    with pytest.raises(InputError, match=f"^simdaq://.*{problem}"):
        serial.serial_for_url(url)
