"""The suite's split: the modules run in parallel (conftest.COMPUTE_MODULES) start nothing and read no clock."""

import re
from pathlib import Path

from conftest import COMPUTE_MODULES

HERE = Path(__file__).parent
# What a test that needs the machine to itself uses: servers and sessions, processes, threads, browsers, clocks.
NEEDS_THE_MACHINE = re.compile(
    r"monotonic|perf_counter|time\(\)|sleep|wait_for|Popen|subprocess|thread|open_session|zenoh|httpx|free_port|free_endpoint|"
    r"chromium|playwright|marionette|\bserve\b",
    re.IGNORECASE,
)


def test_every_parallel_module_exists_and_is_pure_computation():
    assert COMPUTE_MODULES <= {p.name for p in HERE.glob("test_*.py")}, sorted(COMPUTE_MODULES - {p.name for p in HERE.glob("test_*.py")})
    found = {name: sorted(set(NEEDS_THE_MACHINE.findall((HERE / name).read_text()))) for name in sorted(COMPUTE_MODULES)}
    assert not {k: v for k, v in found.items() if v}, found


def test_the_pattern_catches_what_it_names():
    # A module that waits on a clock or starts a server is caught (the check above cannot pass vacuously).
    assert NEEDS_THE_MACHINE.search("deadline = time.monotonic() + 5")
    assert NEEDS_THE_MACHINE.search("proc = subprocess.Popen([sys.executable])")
    assert NEEDS_THE_MACHINE.search("with open_session(connect=[ep]) as s:")
    assert NEEDS_THE_MACHINE.search('main(["serve", "--config", str(cfg)])')
    assert not NEEDS_THE_MACHINE.search("np.testing.assert_allclose(a, b, atol=1e-6); ExtendedKeyUsageOID.SERVER_AUTH")
