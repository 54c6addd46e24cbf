"""The event-loop lag statistics the daemon shows in status (lathed/looplag.py)."""
from lathed.looplag import EDGES_MS, LagStats


def test_window_forgets_old_wakes_and_histogram_keeps_them():
    st = LagStats(window_s=10.0)
    for i in range(80):                  # 79 prompt wakes and one 700 ms stall, 0.125 s apart
        st.add(i * 0.125, 700.0 if i == 40 else 1.5)
    s = st.summary()
    assert s["n"] == 80 and s["p50"] == 1.5 and s["p99"] == 700.0 and s["max"] == 700.0
    for i in range(80, 250):             # 25 s later the stall has left the 10 s window
        st.add(i * 0.125, 3.0)
    s = st.summary()
    assert s["max"] == 3.0 and s["p99"] == 3.0 and s["n"] == 81
    hist = s["since_start"]
    assert hist["n"] == 250 and hist["max"] == 700.0 and hist["edges_ms"] == list(EDGES_MS)
    assert hist["counts"][EDGES_MS.index(1000)] == 1     # (500, 1000] ms
    assert hist["counts"][EDGES_MS.index(2)] == 79 and hist["counts"][EDGES_MS.index(5)] == 170


def test_p99_sees_one_slow_wake_in_fifty():
    st = LagStats()
    for i in range(50):
        st.add(i * 0.05, 80.0 if i == 7 else 0.5)
    assert st.summary()["p99"] == 80.0 and st.summary()["p50"] == 0.5


def test_a_stall_counts_the_wakes_it_swallowed():
    st = LagStats(window_s=60.0)
    for i in range(1000):                # 50 s of prompt 50 ms wakes
        st.add(i * 0.05, 0.5, 50.0)
    st.add(50.0 + 2.0, 2000.0, 50.0)     # then a 2 s freeze: 40 wakes that never happened
    s = st.summary()
    assert s["since_start"]["n"] == 1000 + 40
    assert s["p99"] > 50.0               # one sample alone would leave p99 at 0.5 ms
    assert s["max"] == 2000.0
