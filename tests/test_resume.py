"""Nothing lost on failure: one run per output folder, and an interrupted run says what it
kept and how to resume (`paper`, `evaluate`, `scenes`; docs/evaluation.md, "Batches and
saved progress")."""

from __future__ import annotations

import os
from pathlib import Path
from types import SimpleNamespace

import pytest

from tofloc import api
from tofloc.cli import main
from tofloc.locks import FOLDER_LOCK_NAME, LockedError, OutputLock


def _no_work(*a: object, **k: object) -> None:
    raise AssertionError("the work started although another run holds the folder")


def _interrupt(*a: object, **k: object) -> None:
    raise KeyboardInterrupt


@pytest.fixture
def fake_logs(monkeypatch: pytest.MonkeyPatch) -> None:
    """``evaluate``'s logs, prepared without reading a file (the lock and the note come after)."""
    import evaluation.evaluate as ev

    monkeypatch.setattr(ev, "prepare_logs", lambda logs, **k: [SimpleNamespace(k=10, map_path=Path("m.ply"))])


def test_a_second_run_into_the_same_folder_is_refused_naming_the_first(tmp_path: Path, monkeypatch, capsys,
                                                                       fake_logs: None) -> None:
    import evaluation.evaluate as ev
    import evaluation.paper_data as pd

    monkeypatch.setattr(pd, "prepare_data", _no_work)
    monkeypatch.setattr(ev, "oracle_floor", _no_work)
    out = tmp_path / "run"
    out.mkdir()
    with OutputLock.folder(out):  # the first run, still going
        assert main(["paper", "--trials", "1", "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert f"{out} is in use by pid {os.getpid()}" in " ".join(err.split())
        assert main(["scenes", "--estimators", "icp_pf", "--out", str(out)]) == 2
        assert "is in use by pid" in capsys.readouterr().err
        with pytest.raises(LockedError, match="is in use by pid"):
            api.evaluate(["a.h5"], ["icp_pf"], out=out, trials=1)
        assert sorted(p.name for p in out.iterdir()) == [FOLDER_LOCK_NAME]  # nothing else was written
    assert list(out.iterdir()) == []  # released with the first run


def test_the_lock_is_released_when_the_run_ends(tmp_path: Path, monkeypatch) -> None:
    import evaluation.paper_data as pd

    monkeypatch.setattr(pd, "prepare_data", _interrupt)
    (tmp_path / "run").mkdir()
    with pytest.raises(KeyboardInterrupt):
        api.paper(["icp_pf"], out=tmp_path / "run", trials=1)
    assert list((tmp_path / "run").iterdir()) == []  # no lock file left
    with OutputLock.folder(tmp_path / "run"):  # free again
        pass


def test_an_interrupted_paper_says_what_it_kept_and_how_to_resume(tmp_path: Path, monkeypatch, capsys) -> None:
    import evaluation.paper_data as pd

    out = tmp_path / "run"
    (out / "partial").mkdir(parents=True)
    for name in ("icp_pf__knn__paper.json", "icp_pf__knn__offset.json"):
        (out / "partial" / name).write_text("{}")
    monkeypatch.setattr(pd, "prepare_data", _interrupt)
    notes = api.NoteList()
    with pytest.raises(KeyboardInterrupt) as info:
        api.paper(["icp_pf"], out=out, trials=1, reporter=notes)
    kept = [n for n in notes.notes if n.startswith("kept")]
    assert kept == [f"kept 2 saved batches in {out / 'partial'}; the same command again (same arguments) reuses "
                    "every batch this run finished and runs only the rest"]
    assert info.value.__notes__ == kept  # for a script, on the exception too
    # the CLI prints it (then "interrupted" for a real Ctrl-C), exit code 130, no traceback
    assert main(["paper", "--trials", "1", "--out", str(out)]) == 130
    err = capsys.readouterr().err
    assert "kept 2 saved batches" in err and "Traceback" not in err


def test_an_interrupted_evaluate_says_what_it_kept(tmp_path: Path, monkeypatch, fake_logs: None) -> None:
    import evaluation.evaluate as ev

    out = tmp_path / "run"
    (out / "partial").mkdir(parents=True)
    (out / "partial" / "node__icp_pf.json").write_text("{}")
    monkeypatch.setattr(ev, "oracle_floor", _interrupt)
    notes = api.NoteList()
    with pytest.raises(KeyboardInterrupt):
        api.evaluate(["a.h5"], ["icp_pf"], out=out, trials=1, reporter=notes)
    assert [n for n in notes.notes if n.startswith("kept")] == [
        f"kept 1 saved batch in {out / 'partial'}; the same command again (same arguments) reuses every batch this "
        "run finished and runs only the rest"]


def test_an_interrupted_scenes_run_counts_every_scene_once(tmp_path: Path, monkeypatch) -> None:
    """``scenes`` runs ``paper`` per scene: one note, from the outer run, over every scene's
    batches in the folder (a scene of an earlier run among them: counted as saved, and the
    note promises reuse only of this run's)."""
    import evaluation.paper_data as pd

    out = tmp_path / "run"
    for scene in ("paper-exact", "pillars-exact"):
        (out / scene / "partial").mkdir(parents=True)
        (out / scene / "partial" / "icp_pf__mocap__offset.json").write_text("{}")
    monkeypatch.setattr(pd, "prepare_data", _interrupt)
    notes = api.NoteList()
    with pytest.raises(KeyboardInterrupt) as info:
        api.scenes(["icp_pf"], out=out, scene_names=["paper"], trials=1, reporter=notes)
    kept = [n for n in notes.notes if n.startswith("kept")]
    assert kept == [f"kept 2 saved batches in 2 partial/ folders under {out}; the same command again (same "
                    "arguments) reuses every batch this run finished and runs only the rest"]
    assert info.value.__notes__ == kept


def test_a_run_refused_once_it_started_leaves_no_empty_folder(tmp_path: Path) -> None:
    """The folder made for the lock goes again when the run wrote nothing (an unknown scene
    is found by the data step, after the lock was taken)."""
    out = tmp_path / "run"
    assert main(["paper", "--scenario", "no_such_scene", "--trials", "1", "--out", str(out)]) == 2
    assert not out.exists()


def test_a_saved_batch_is_reused_only_when_its_records_are_sound() -> None:
    from evaluation.result_cache import usable_records

    good = [{"k": k, "trial": t, "seed": 7 + t, "e_x_m": 0.01, "e_gamma_deg": 0.5} for k in (1, 5) for t in range(2)]
    assert usable_records(good, [1, 5], 2)
    assert usable_records([dict(r, e_x_m=None, e_gamma_deg=None) for r in good], [1, 5], 2)  # no truth
    for bad in (good[:3], good + good[:1], [dict(good[0], e_x_m=-3.0)] + good[1:], [dict(good[0], e_gamma_deg=float("nan"))] + good[1:],
                [dict(good[0], k=True)] + good[1:], [dict(good[0], trial=1)] + good[1:], [{"seed": 1}] * 4, "records", None):
        assert not usable_records(bad, [1, 5], 2)
