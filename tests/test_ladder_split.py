"""Where the ladder's runs hand over (planners.cutpath.ladder._split, _balanced): the fewest runs, met
where none is left a stub."""

import numpy as np

from planners.cutpath.ladder import _balanced, _split, _stubs


def _ladder(n: int, spans: list[tuple[int, int]]):
    """(usable (n,R), edges(k, usable)) for one rung per configuration family, usable over its layer
    span (first, last) and joining only itself from layer to layer."""
    usable = np.zeros((n, len(spans)), bool)
    for r, (a, b) in enumerate(spans):
        usable[a:b + 1, r] = True

    def edges(k: int, u: np.ndarray) -> np.ndarray:
        return np.diag(u[k] & u[k + 1])

    return usable, edges


def test_a_stub_between_two_reconfigurations_starts_earlier_where_its_configuration_reaches_back():
    """Three families over 16 layers 5 mm apart: the greedy split hands over as late as it can and leaves
    the middle run one step (5 mm) long; the middle family reaches back to layer 3, so the hand-over
    moves to where both runs are 20 mm at least. Three runs still, joined end to start."""
    usable, edges = _ladder(16, [(0, 8), (3, 9), (9, 15)])
    s = 0.005 * np.arange(16)
    greedy = _split(16, usable, edges)
    assert greedy == [(0, 8), (8, 9), (9, 15)]
    runs = _balanced(greedy, usable, edges, s, 0.02)
    assert runs == [(0, 5), (5, 9), (9, 15)]
    assert all(s[b] - s[a] >= 0.02 - 1e-12 for a, b in runs)
    # where the middle family reaches back no further, the stub stays (a pierce for it, not a gap)
    usable, edges = _ladder(16, [(0, 8), (8, 9), (9, 15)])
    assert _balanced(_split(16, usable, edges), usable, edges, s, 0.02) == [(0, 8), (8, 9), (9, 15)]
    # a run after a gap is nobody's hand-over: untouched
    usable, edges = _ladder(16, [(0, 5), (8, 9), (9, 15)])
    assert _balanced(_split(16, usable, edges), usable, edges, s, 0.02) == [(0, 5), (8, 9), (9, 15)]


def test_a_stub_between_two_gaps_is_no_cut_but_one_the_torch_hands_over_to_is():
    """5 mm runs, 20 mm the least cut: between two stretches left uncut (or the branch's ends) it is a
    pierce for nothing; beside a reconfiguration it cuts its paint (nothing is left uncut between the two
    runs); one without length never cuts."""
    s = 0.005 * np.arange(16)
    assert _stubs([(3, 4), (8, 15)], s, 0.02, 0.005) == [True, False]  # gaps either side
    assert _stubs([(0, 1), (3, 15)], s, 0.02, 0.005) == [True, False]  # the branch's start, then a gap
    assert _stubs([(3, 4), (4, 15)], s, 0.02, 0.005) == [False, False]  # hands over to the next
    assert _stubs([(0, 8), (8, 9), (9, 15)], s, 0.02, 0.005) == [False, False, False]
    assert _stubs([(0, 8), (8, 8), (8, 15)], s, 0.02, 0.005) == [False, True, False]  # no length at all
