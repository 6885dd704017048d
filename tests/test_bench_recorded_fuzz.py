"""The target for recorded input: a fuzz of recorded arcs, S-curves, U-turns and lane changes (5 mm
to 10 cm apart, 0 to 20 mm of noise) at the default tolerance, drawn by bench/recorded_fuzz.py
(`python -m bench.recorded_fuzz --n 200 --seed S` runs more), loads with none refused as a
reversal, and each completes in time."""

from __future__ import annotations

import pytest

from bench import recorded_fuzz as fz


def test_recorded_paths_load_at_the_default_tolerance() -> None:
    """No curve refused, no arc turned in place, no other curve but a U-turn turned back."""
    bad = [fz.line(o) for o in (fz.check(r, sim=False) for r in fz.recordings(80, 23))
           if o.error or not fz.Outcome(o.rec, completed=True, sim_s=0.0, pivots=o.pivots,
                                        largest_turn_deg=o.largest_turn_deg).ok]
    assert not bad, "\n".join(bad)


@pytest.mark.slow
def test_recorded_paths_complete_in_time() -> None:
    """Each completes in `ddrt sim` within 1.3 x length / speed + 3 s."""
    outs = [fz.check(r) for r in fz.recordings(60, 22)]
    bad = [fz.line(o) for o in outs if not o.ok]
    assert not bad, "\n".join(bad)
