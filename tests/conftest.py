import os

import numpy as np
import pytest

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


# The stability suite prints its invariants ("[stability] ..." lines); show them in the
# summary of every run, passed or not, without -s.
_STABILITY_LINES = []


def pytest_runtest_logreport(report):
    if report.when == "call":
        _STABILITY_LINES.extend(l for l in report.capstdout.splitlines() if l.startswith("[stability]"))


def pytest_terminal_summary(terminalreporter):
    if _STABILITY_LINES:
        terminalreporter.section("stability invariants")
        for line in _STABILITY_LINES:
            terminalreporter.write_line(line)
