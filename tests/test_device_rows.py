"""A device's channels worked together (lathed.analysis.device_rows): each channel's cut state
the same, bit for bit, as its own alone; one channel's bad data or stopped reader leaves the
others as they were."""
from __future__ import annotations

import numpy as np
import pytest

from lathed.analysis.conditioning import Conditioner, ConditionerBank
from lathed.analysis.cut.sources import VibrationCutDetector
from lathed.analysis.device_rows import DeviceRows
from lathed.analysis.regen import Segment as S, simulate_cut
from lathed.sim.lathe import LATHE_KF, LATHE_MODES

RATE = 51200.0
BLOCK = 1024


def _signals(n: int) -> np.ndarray:
    """Frames x channels, full scale: cuts entering and leaving at different times and gains."""
    cols = []
    for i in range(n):
        rec = simulate_cut([S(0.2 + 0.05 * i, 3000, 0.0), S(0.4, 3000, 0.6 + 0.1 * i), S(0.5, 3000, 0.0)],
                           modes=LATHE_MODES, kf_n_per_m2=LATHE_KF, seed=10 + i)
        cols.append(rec.signal[:int(1.05 * RATE)] / (40.0 * (i + 1)))
    return np.stack(cols, axis=1).astype(np.float32)


def _state(det: VibrationCutDetector) -> bytes:
    # everything the detector says or carries on, as bytes (NaN compared as itself)
    nums = [det.floor, det.entry_jump, *det._last_rms, det._quiet, det._run,
            -1 if det.contact is None else det.contact, {None: -1, False: 0, True: 1}[det.cutting]]
    return np.array(nums, float).tobytes() + np.asarray(det._rest, float).tobytes()


class Counted(DeviceRows):
    served = 0

    def frame_rms(self, frame, k, row):
        got = super().frame_rms(frame, k, row)
        Counted.served += got is not None
        return got


@pytest.fixture
def counted(monkeypatch):
    import lathed.analysis.conditioning as conditioning
    monkeypatch.setattr(conditioning, "DeviceRows", Counted)
    Counted.served = 0
    return Counted


def test_each_channels_cut_state_is_its_own_bit_for_bit(counted):
    x = _signals(4)
    x[int(0.5 * RATE):int(0.5 * RATE) + 300, 1] = np.inf        # one channel's bad data
    bank = ConditionerBank()
    members = ["a", "b", "c", "d"]
    for col, m in enumerate(members):
        bank.join(m, Conditioner(RATE, 9.8 * (col + 1), 2.0), col)
    alone = {m: (Conditioner(RATE, 9.8 * (col + 1), 2.0), VibrationCutDetector(RATE)) for col, m in enumerate(members)}
    shared = {m: VibrationCutDetector(RATE) for m in members}
    # "d" frames differently: it cannot share the others' frames and works alone throughout
    alone["d"] = (alone["d"][0], VibrationCutDetector(RATE, frame_s=0.003))
    shared["d"] = VibrationCutDetector(RATE, frame_s=0.003)
    entries = dict.fromkeys(members, 0)
    blocks = len(x) // BLOCK
    for b in range(blocks):
        data = x[b * BLOCK:(b + 1) * BLOCK].copy()
        if b in (9, 10):
            data[:, 2] = 0.0          # digital silence on "c": its row is not in the block's rows
        for m in members:
            _, _, y, at = bank.take(m, data)
            cond, det = alone[m]
            if y is None:
                assert at is None
                continue
            own = cond.process(np.ascontiguousarray(data[:, members.index(m)]))
            assert own.tobytes() == y.tobytes()
            if m == "b" and 20 <= b < 24:
                continue              # "b"'s reader stopped a while (restarted: a fresh detector)
            if m == "b" and b == 24:
                alone["b"] = (cond, VibrationCutDetector(RATE))
                shared["b"] = VibrationCutDetector(RATE)
                det = alone["b"][1]
            rows, row = at
            assert rows.ys[row] is y
            got = shared[m].process(y, rows, row)
            want = det.process(own)
            entries[m] += want is not None
            assert got == want and _state(shared[m]) == _state(det), (m, b)
    # the cuts' entries and exits were in it ("b" is blind from its bad data on)
    assert entries["a"] >= 2 and entries["c"] >= 2 and entries["d"] >= 2, entries
    # each was served with the others that frame alike but for its first block and the one
    # after it missed blocks ("c"'s silence, "b"'s stop, each then at its own offset)
    assert counted.served >= 4 * blocks - 4 - 2 - 2 - 4 - 2


def test_a_reader_two_blocks_behind_works_alone():
    # the rows keep the two latest blocks: an older block's frames are not made together
    x = _signals(2)
    bank = ConditionerBank()
    for col, m in enumerate("ab"):
        bank.join(m, Conditioner(RATE, 9.8, 2.0), col)
    got = [bank.take("a", x[b * BLOCK:(b + 1) * BLOCK])[3][0] for b in range(4)]
    assert got[0].ys is None and got[1].ys is None and got[2].prev is None
    assert got[3].prev is got[2] and got[2].ys is not None
    got[2].ask(204, 12, 0)
    assert got[3].frame_rms(204, 12, 0) is not None
    assert got[3].frame_rms(205, 12, 0) is None and got[3].frame_rms(204, 12, 1) is None   # not asked
    got[1].ask(204, 8, 0)
    assert got[2].frame_rms(204, 8, 0) is None      # its block before is let go
