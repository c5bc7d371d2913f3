"""The CAN accelerometer driver on a python-can `virtual` bus, fed by the rig's nodes: samples equal the truth."""
from __future__ import annotations

import uuid

import numpy as np
import pytest

from odsplat.acquisition import canproto as cp
from odsplat.acquisition.can_nodes import CANAccelerometers, CANError
from odsplat.hil_sim.can_nodes import CANFaults, sim_nodes
from odsplat.hil_sim.rig import SimRig

pytestmark = pytest.mark.timeout(60)
RANGE = cp.RANGES_M_S2[4]  # +-50 g


def test_nodes_stream_into_the_ring_in_si_units_with_gaps_left_nan(scene):
    rig = SimRig(scene)
    rig.hit(0.1)
    channel = f"odsplat-acq-{uuid.uuid4().hex}"
    faults = {1: CANFaults(drop_every=100), 2: CANFaults()}
    with sim_nodes(channel, [1, 2], rig, faults=faults, sample_rate_hz=1000.0, range_m_s2=RANGE) as nodes:
        acc = CANAccelerometers.open([1, 2], interface="virtual", channel=channel, sample_rate_hz=1000.0,
                                     range_m_s2=RANGE)
        acc.start()
        acc.wait_for(1, 1000, timeout_s=10)
        acc.wait_for(2, 1000, timeout_s=10)
        got = {n: acc.read(n, 0, 1000) for n in (1, 2)}
        acc.stop()
    lsb = RANGE / cp.FULL_SCALE_COUNTS
    truth = rig.truth(1, daq_rate_hz=25600.0)
    for i, mount in enumerate(rig.config.can_nodes):
        phi = truth.sensor_mode_shapes[len(rig.config.accelerometers) + i]
        t = mount.t0_s + np.arange(1000) / 1000.0
        qdd = scene.structure.modal_response(rig.impacts, t).qdd
        expected = np.einsum("kc,kt->tc", phi, qdd) @ np.asarray(mount.axes).T
        ok = ~np.isnan(got[mount.node_id][:, 0])
        assert np.max(np.abs(got[mount.node_id][ok] - expected[ok])) <= 0.5 * lsb + 1e-9
    lost = np.flatnonzero(np.isnan(got[1][:, 0]))
    assert lost.tolist() == list(range(99, 1000, 100)) == sorted(nodes[0].dropped_samples[:10])
    assert not np.isnan(got[2]).any()
    assert [(g.node_id, g.first_sample) for g in acc.gaps][:3] == [(1, 99), (1, 199), (1, 299)]
    np.testing.assert_allclose(acc.times_s(0, 3), [0.0, 1e-3, 2e-3])


def test_a_silent_node_is_named(scene):
    rig = SimRig(scene)
    channel = f"odsplat-acq-{uuid.uuid4().hex}"
    with sim_nodes(channel, [1], rig, faults={1: CANFaults(disconnect_after_samples=300)}):
        acc = CANAccelerometers.open([1], interface="virtual", channel=channel, node_timeout_s=0.2)
        acc.start()
        with pytest.raises(CANError, match="node 1 went silent at sample 300"):
            acc.wait_for(1, 1000, timeout_s=10)
        acc.stop()
