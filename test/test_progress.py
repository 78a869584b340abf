"""Progress bars: tqdm's redraws on a terminal, whole throttled lines in a log file."""

from __future__ import annotations

import io

from t42_transfer.models.training import Progress, ProgressBar
from t42_transfer.progress import progress_bar


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def run_bar(out: io.StringIO, steps: int = 1000, **kwargs) -> str:
    with progress_bar(file=out, total=steps, desc="train", unit="ep", **kwargs) as bar:
        for step in range(steps):
            bar.set_postfix(loss=f"{step:.1f}")  # forces a redraw each step, as the training bar does
            bar.update()
    return out.getvalue()


def test_in_a_log_file_a_fast_bar_is_its_first_and_final_lines() -> None:
    lines = run_bar(io.StringIO(), leave=False).splitlines()
    assert len(lines) == 2, lines
    assert lines[0].startswith("train:   0% 0/1000")
    assert lines[1].startswith("train: 100% 1000/1000") and "loss=999.0" in lines[1]  # kept despite leave=False
    assert all("\r" not in line and "|" not in line for line in lines)


def test_in_a_log_file_each_redraw_past_the_interval_is_a_line() -> None:
    lines = run_bar(io.StringIO(), steps=20, mininterval=0.0).splitlines()
    assert len(lines) >= 20 and len(set(lines)) == len(lines), lines
    assert [line.split()[2] for line in lines[-20:]] == [f"{n}/20" for n in range(1, 21)]


def test_on_a_terminal_the_bar_redraws_in_place() -> None:
    text = run_bar(Terminal(), steps=5, leave=False)
    assert text.count("\r") >= 2 and "|" in text


def test_the_training_hook_writes_each_phase_to_a_log_as_lines(capsys) -> None:
    hook = ProgressBar()
    for phase, epochs in (("source", 3), ("finetune", 2)):
        for epoch in range(1, epochs + 1):
            hook(Progress(phase=phase, epoch=epoch, epochs=epochs, train_loss=0.5 / epoch, val_loss=None))
    err = capsys.readouterr().err
    assert "\r" not in err
    finals = [line for line in err.splitlines() if " 100% " in line]
    assert [line.split(":")[0] for line in finals] == ["source", "finetune"], err
    assert "3/3" in finals[0] and "2/2" in finals[1] and "val=-" in finals[1]


def test_in_a_log_file_a_bar_inside_another_keeps_to_the_interval() -> None:
    out = io.StringIO()
    with progress_bar(file=out, total=3, desc="outer") as outer:
        for _ in range(3):
            run_bar(out, steps=200)  # an inner bar redrawn at every step
            outer.update()
    lines = out.getvalue().splitlines()
    assert len(lines) <= 2 + 3 * 2, lines  # each bar's first and final lines
    assert lines[-1].startswith("outer: 100% 3/3") and "\r" not in out.getvalue()
