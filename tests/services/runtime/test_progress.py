"""The progress line: an estimate from the error's decay, shown on a terminal only."""
import io
import math

from services.runtime.progress import ProgressLine, iterations_left


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_the_iterations_left_follow_the_error_s_exponential_decay():
    errors = [0.1 * 0.95**k for k in range(30)]
    expected = math.log(errors[-1] / 5e-5) / -math.log(0.95)
    assert abs(iterations_left(errors, 5e-5, 29, 1000) - expected) <= 1
    assert iterations_left(errors, 5e-5, 29, 40) == 11  # never past the run's last iteration
    assert iterations_left(errors[:3], 5e-5, 2, 1000) is None  # no rate yet
    assert iterations_left([0.1] * 20, 5e-5, 19, 600) == 581  # not decaying: as long as the run may go
    assert iterations_left(errors + [1e-5], 5e-5, 30, 600) == 0


def test_the_line_is_written_on_a_terminal_and_nowhere_else():
    terminal = Terminal()
    line = ProgressLine("table3 p-joint", 5e-5, 600, stream=terminal)
    for k in range(10):
        line.update(k, 0.1 * 0.9**k)
    line.done()
    text = terminal.getvalue()
    assert "table3 p-joint: iteration     9" in text and "ETA" in text and text.endswith("\r")
    piped = io.StringIO()
    quiet = ProgressLine("x", 5e-5, 600, stream=piped)
    quiet.update(1, 0.1)
    quiet.done()
    assert piped.getvalue() == ""
    assert ProgressLine("x", 5e-5, 600, enabled=False, stream=Terminal()).enabled is False
