"""Progress bars (patexgs_jax.progress): drawn on stderr with a count and an ETA when forced or on a
terminal, absent when stderr is not a terminal, and never in the way of the printed lines."""

from __future__ import annotations

import re

from patexgs_jax import progress


def _use(n=3):
    with progress.bar(n, "work", unit="view") as bar:
        for i in range(n):
            progress.say(f"line {i}")
            bar.update(1)


def test_no_bar_when_stderr_is_not_a_terminal(capfd, monkeypatch):
    monkeypatch.delenv(progress.ENV_VAR, raising=False)
    assert not progress.enabled()  # pytest's captured stderr is a file, not a terminal
    _use()
    out, err = capfd.readouterr()
    assert err == ""
    assert out.splitlines() == ["line 0", "line 1", "line 2"]
    monkeypatch.setenv(progress.ENV_VAR, "0")
    assert not progress.enabled()


def test_forced_bar_shows_count_and_eta_and_keeps_lines_whole(capfd, monkeypatch):
    monkeypatch.setenv(progress.ENV_VAR, "1")
    _use()
    out, err = capfd.readouterr()
    assert out.splitlines() == ["line 0", "line 1", "line 2"]  # printed above the bar, not through it
    # "work:  67%|██████▋   | 2/3 [00:00<00:00, ...view/s]": count, elapsed<remaining (the ETA), rate
    assert re.search(r"work: +\d+%\|.*\| [0-3]/3 \[\d\d:\d\d<\d\d:\d\d, [^]]*view/s\]", err), err
    with progress.bar(5, "hidden", show=False) as bar:  # a caller's own switch (verbose=False, process > 0)
        bar.update(5)
    assert "hidden" not in capfd.readouterr().err
