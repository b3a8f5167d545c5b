"""The demo's one line on touch says which way the Chamfer distance went."""

from tacsplat.apps.demo import _change


def test_a_touch_that_helps_reads_lower_and_one_that_hurts_reads_higher():
    assert _change(0.0300, 0.0280) == "1.07x lower (0.0300 -> 0.0280)"
    assert _change(0.0288, 0.0314) == "1.09x higher (0.0288 -> 0.0314)"
    assert _change(0.0300, 0.0300) == "1.00x lower (0.0300 -> 0.0300)"
