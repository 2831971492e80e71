"""The host record every benchmark prints beside its figures (common.hostref)."""

import math
import platform

from common.hostref import describe, host_reference


def test_host_reference_times_the_three_references_on_this_host():
    ref = host_reference()
    assert ref["machine"] == platform.machine()
    assert ref["python"] == platform.python_version()
    assert ref["cores"] >= 1
    for key in ("python_loop_ns", "numpy_matmul_24_us", "match_template_us"):
        assert math.isfinite(ref[key]) and ref[key] > 0.0, key
    # a loop iteration is some instructions, not a second; a 24x24 product and a 121x73 SSD are microseconds
    assert 1.0 < ref["python_loop_ns"] < 1e5
    assert ref["numpy_matmul_24_us"] < 1e4 and ref["match_template_us"] < 1e5
    line = describe(ref)
    assert f"{ref['python_loop_ns']:.0f} ns/iteration" in line and ref["cpu"] in line
