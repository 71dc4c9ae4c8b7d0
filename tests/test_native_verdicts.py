"""The fused kernels' check verdicts, recorded per machine: a later process takes the recorded
verdict of the same check of the same code on the same CPU and settings, and checks again for any
other (fr_torch.core.likelihood.native._checked / _verdict_file)."""
import json
import os

import pytest

from fr_torch.core.likelihood import native


@pytest.fixture
def verdict_file(tmp_path, monkeypatch):
    path = tmp_path / "verdicts-test.json"
    monkeypatch.setitem(native._state, "verdict_file", path)
    return path


def test_a_recorded_verdict_is_taken_without_checking_again(verdict_file):
    calls = []

    def check():
        calls.append(1)
        return True

    assert native._checked("kernels", check) is True and len(calls) == 1
    assert json.loads(verdict_file.read_text()) == {"kernels": True}
    assert native._checked("kernels", lambda: pytest.fail("checked again")) is True
    assert native._checked("refine", lambda: False) is False  # another check: run and recorded beside
    assert json.loads(verdict_file.read_text()) == {"kernels": True, "refine": False}


def test_an_unreadable_record_means_checking_again(verdict_file):
    verdict_file.write_text("{not json")
    assert native._checked("kernels", lambda: True) is True
    verdict_file.write_text(json.dumps({"kernels": "yes"}))  # not a verdict
    assert native._checked("kernels", lambda: False) is False


def test_the_record_follows_the_library_the_cpu_settings_and_the_sources(tmp_path, monkeypatch):
    monkeypatch.setitem(native._state, "library", tmp_path / "measure_b-0000.so")
    first = native._verdict_file()
    assert first.parent == tmp_path and first.name.startswith("verdicts-")
    assert native._verdict_file() == first  # the same inputs, the same file
    other = "avx2" if os.environ.get("ATEN_CPU_CAPABILITY") == "default" else "default"  # another kernel set
    monkeypatch.setenv("ATEN_CPU_CAPABILITY", other)
    assert native._verdict_file() != first
    monkeypatch.setitem(native._state, "library", tmp_path / "measure_b-1111.so")
    assert native._verdict_file().name != first.name


def test_a_record_that_cannot_be_written_leaves_nothing_behind(verdict_file, monkeypatch):
    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(native.json, "dump", full_disk)
    assert native._checked("kernels", lambda: True) is True  # the check's verdict, not recorded
    assert list(verdict_file.parent.iterdir()) == []
