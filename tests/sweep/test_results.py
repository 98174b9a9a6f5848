"""The results file: appended lines survive, a torn last line is dropped, a corrupt middle
line is refused, one writer at a time."""

import json

import pytest

from afvsgp_gym.sweep.results import ResultsLog, read_records


def _rec(i: int) -> dict:
    return {"key": f"k{i}", "seed": i, "min_h": float("nan") if i == 2 else 0.1 * i}


def test_append_reopen_and_read(tmp_path):
    path = tmp_path / "sub" / "r.jsonl"
    with ResultsLog(path) as log:
        assert log.records == [] and log.keys == set()
        for i in range(3):
            log.append(_rec(i))
    lines = path.read_text().splitlines()
    assert len(lines) == 3 and json.loads(lines[2])["min_h"] is None  # strict JSON, no NaN
    with ResultsLog(path) as log:
        assert log.keys == {"k0", "k1", "k2"}
        log.append(_rec(3))
    assert [r["key"] for r in read_records(path)] == ["k0", "k1", "k2", "k3"]


def test_torn_last_line_is_dropped_then_overwritten(tmp_path):
    path = tmp_path / "r.jsonl"
    with ResultsLog(path) as log:
        log.append(_rec(0))
        log.append(_rec(1))
    full = path.read_bytes()
    torn = json.dumps(_rec(2)).encode()[:17]  # a write cut short by a kill
    path.write_bytes(full + torn)
    assert [r["key"] for r in read_records(path)] == ["k0", "k1"]  # readers ignore it
    with ResultsLog(path) as log:
        assert log.keys == {"k0", "k1"}
        log.append(_rec(2))
    assert path.read_bytes() == full + (json.dumps(_rec(2), separators=(",", ":"))
                                        .replace("NaN", "null") + "\n").encode()


def test_complete_last_record_without_newline_is_kept(tmp_path):
    path = tmp_path / "r.jsonl"
    path.write_text(json.dumps(_rec(0)) + "\n" + json.dumps(_rec(1)))
    with ResultsLog(path) as log:
        assert log.keys == {"k0", "k1"}
        log.append(_rec(3))
    assert [r["key"] for r in read_records(path)] == ["k0", "k1", "k3"]


def test_corrupt_middle_line_is_refused_untouched(tmp_path):
    path = tmp_path / "r.jsonl"
    text = json.dumps(_rec(0)) + "\n{not json\n" + json.dumps(_rec(1)) + "\n"
    path.write_text(text)
    with pytest.raises(ValueError, match="line 2"):
        ResultsLog(path).__enter__()
    with pytest.raises(ValueError, match="line 2"):
        read_records(path)
    path.write_text(json.dumps(_rec(0)) + "\n[1, 2]\n")
    with pytest.raises(ValueError, match="line 2 is not an episode record"):
        read_records(path)
    assert path.read_text() == json.dumps(_rec(0)) + "\n[1, 2]\n"


def test_one_writer_at_a_time(tmp_path):
    path = tmp_path / "r.jsonl"
    with ResultsLog(path):
        with pytest.raises(RuntimeError, match="another sweep"):
            ResultsLog(path).__enter__()
    with ResultsLog(path) as log:  # released on exit
        log.append(_rec(0))


def test_gzip_archive_reads_the_same_records(tmp_path):
    import gzip

    path = tmp_path / "r.jsonl"
    with ResultsLog(path) as log:
        for i in range(3):
            log.append(_rec(i))
    archived = tmp_path / "r.jsonl.gz"
    archived.write_bytes(gzip.compress(path.read_bytes()))
    assert read_records(archived) == read_records(path)
    broken = tmp_path / "broken.jsonl.gz"
    broken.write_bytes(archived.read_bytes()[:20])  # a truncated archive
    with pytest.raises(ValueError, match="broken.jsonl.gz"):
        read_records(broken)
