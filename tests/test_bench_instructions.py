"""bench.instructions: reading valgrind's count and choosing the steady cycles to count."""

import pytest

from bench.instructions import parse_irefs, steady_window

CACHEGRIND = """==4242== Cachegrind, a high-precision tracing profiler
==4242== Command: python -m bench.instructions flight.pickle planner 300
==4242==
==4242== I   refs:      2,148,958,608
"""


def test_the_instruction_count_is_read_from_cachegrinds_report() -> None:
    assert parse_irefs(CACHEGRIND) == 2_148_958_608


def test_a_report_without_a_count_is_an_error_that_shows_it() -> None:
    with pytest.raises(RuntimeError, match="no instruction count"):
        parse_irefs("==1== valgrind: failed to start tool 'cachegrind'")


def test_the_window_is_the_first_steady_stretch_after_the_warmup() -> None:
    searching = [False] * 50
    searching[12] = searching[30] = True
    assert steady_window(searching, cycles=10, warmup=5) == (13, 23)
    assert steady_window(searching, cycles=17, warmup=5) == (13, 30)
    assert steady_window(searching, cycles=5, warmup=0) == (0, 5)


def test_without_a_stretch_that_long_the_longest_one_is_counted() -> None:
    searching = [False] * 40
    searching[10] = searching[25] = True
    assert steady_window(searching, cycles=30, warmup=0) == (11, 25)
    assert steady_window(searching, cycles=30, warmup=26) == (26, 40)
