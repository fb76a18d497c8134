"""Status of long steps: the records the library sends (`inrslam.status`), the initialisation counter, and how
`inrslam run` shows them (lines, bars, ETA). No SLAM run."""

from __future__ import annotations

import io
import logging
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from rich.console import Console

from inrslam.cli import _status_display, _StatusDisplay, eta_text
from inrslam.status import LOGGER, logger, progress, progress_of, stage


def records(caplog) -> list[tuple[str, tuple[int, int] | None]]:
    return [(r.getMessage(), progress_of(r)) for r in caplog.records if r.name.startswith(LOGGER)]


def test_stage_and_progress_records(caplog):
    log = logger("inrslam.runner")
    assert log.name == "inrslam.runner" and logger("eval.run").name == "inrslam.eval.run"
    with caplog.at_level(logging.INFO, logger=LOGGER):
        stage(log, "extracting the mesh")
        progress(log, "renders", 2, 5)
    assert records(caplog) == [("extracting the mesh", None), ("renders", (2, 5))]


def fake_system(init_iters: int):
    p = torch.nn.Parameter(torch.ones(3))
    opt = torch.optim.SGD([p], lr=0.1)
    return SimpleNamespace(cfg=SimpleNamespace(slam=SimpleNamespace(init_iters=init_iters)),
                           state=SimpleNamespace(optimizers={"field": opt, "other": torch.optim.SGD([p], lr=0.0)})), p


def steps(opt, p, n: int) -> None:
    for _ in range(n):
        opt.zero_grad()
        (p ** 2).sum().backward()
        opt.step()


def test_initialisation_is_counted_by_a_hook_that_only_observes(caplog):
    from inrslam.runner import INIT_UPDATES, _initialisation_status

    system, p = fake_system(init_iters=120)
    opt = system.state.optimizers["field"]
    with caplog.at_level(logging.INFO, logger=LOGGER), _initialisation_status(system):
        steps(opt, p, 120)
    got = records(caplog)
    assert got[0][0].startswith("initialising the map on frame 0 (120 iterations") and got[0][1] is None
    counts = [c for _, c in got[1:]]
    assert len(counts) <= INIT_UPDATES and counts[-1] == (120, 120)
    assert all(c[1] == 120 for c in counts) and [c[0] for c in counts] == sorted(c[0] for c in counts)
    assert not opt._optimizer_step_post_hooks  # removed afterwards
    plain, q = fake_system(init_iters=120)
    steps(plain.state.optimizers["field"], q, 120)
    assert torch.equal(p, q)  # the same steps with and without the counter


def test_heldout_renders_report_their_progress(caplog):
    from inrslam.eval.heldout import heldout_metrics

    frame = SimpleNamespace(rgb=np.full((12, 12, 3), 0.5), depth=np.ones((12, 12)), intrinsics=None)
    dataset = [frame] * 9
    render = lambda c2w, intr: (np.full((12, 12, 3), 0.5), np.ones((12, 12)))  # noqa: E731
    with caplog.at_level(logging.INFO, logger=LOGGER):
        out = heldout_metrics(render, dataset, [np.eye(4)] * 9, every=3, max_frames=10)
    assert out["heldout_frames"] == [0, 3, 6]
    assert records(caplog) == [("renders", (1, 3)), ("renders", (2, 3)), ("renders", (3, 3))]


def test_evaluation_says_what_it_computes(tmp_path, caplog):
    from inrslam.bench.testing import write_fake_run
    from inrslam.eval.run import evaluate_run

    run = write_fake_run(tmp_path / "run", "dense", "density", frames=10)
    with caplog.at_level(logging.INFO, logger=LOGGER):
        evaluate_run(run)
    assert ("evaluation: ATE / RPE of 10 poses (se3 alignment)", None) in records(caplog)


def test_eta_from_the_rate_so_far():
    assert eta_text(10.0, 5, 10) == "ETA 0:20"
    assert eta_text(100.0, 1, 40) == "ETA 1:06:40"
    assert eta_text(0.0, 0, 10) == "ETA –" and eta_text(5.0, 5, 0) == ""


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def test_display_prints_timed_lines_and_bars_with_an_eta():
    out = io.StringIO()
    clock = Clock()
    display = _StatusDisplay(Console(file=out, width=120, force_terminal=False), t0=0.0, clock=clock)
    clock.t = 2.0
    display.line("opening the dataset builtin:room")
    display.count("init", 10, 60)
    clock.t = 4.0
    display.count("init", 20, 60)
    task = display.prog.tasks[0]
    assert task.fields["info"] == "ETA 0:08" and task.completed == 20  # 10 steps in 2 s, 40 to go
    display.count("init", 60, 60)
    assert display.prog.tasks[0].fields["info"] == ""  # finished: no ETA
    clock.t = 12.5
    display.line("extracting the mesh")  # all bars done: they stop, the line goes below them
    assert display.prog is None
    text = out.getvalue()
    assert "   2.0 s  opening the dataset builtin:room" in text and "  12.5 s  extracting the mesh" in text
    assert text.index("opening") < text.index("init") < text.index("extracting the mesh")


def test_status_display_receives_the_library_records_while_it_is_open():
    out = io.StringIO()
    console = Console(file=out, width=120, force_terminal=False)
    root = logging.getLogger(LOGGER)
    handlers, level = list(root.handlers), root.level
    with _status_display(console, quiet=False) as display:
        stage(logger("inrslam.eval.run"), "evaluation: culling the mesh")
        progress(logger("inrslam.eval.heldout"), "renders", 1, 2)
        assert display.tasks and "renders" in display.tasks
    assert root.handlers == handlers and root.level == level  # everything put back
    stage(logger("inrslam.eval.run"), "after the display closed")
    assert "evaluation: culling the mesh" in out.getvalue() and "after the display closed" not in out.getvalue()
    with _status_display(console, quiet=True) as display:
        assert display is None


@pytest.mark.parametrize("argv", [["run", "--help"], ["run", "-h"]])
def test_run_help_still_lists_the_registries(argv, capsys):
    from inrslam.cli import main

    with pytest.raises(SystemExit):
        main(argv)
    assert "hash" in capsys.readouterr().out


def test_initialisation_bar_ends_even_when_steps_were_skipped(caplog):
    from inrslam.runner import _initialisation_status

    system, p = fake_system(init_iters=10)
    with caplog.at_level(logging.INFO, logger=LOGGER), _initialisation_status(system):
        steps(system.state.optimizers["field"], p, 7)  # three iterations took no step
    assert records(caplog)[-1] == ("init", (10, 10))
