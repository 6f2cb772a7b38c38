"""benchmarks/records.py: rerunning a benchmark's documented command writes its new run and keeps the
sections added to its record below the generated run (other machines, findings, A/B runs)."""

from repo_scripts import load_script


def _records():
    return load_script("benchmarks/records.py")


def test_rerun_keeps_added_sections_and_replaces_its_own(tmp_path):
    path = tmp_path / "record.md"
    path.write_text("# Title\n\nold run\n\n## Generated table\nold rows\n\n## A finding (another CPU)\nkept text\n")
    _records().write_record(path, "# Title\n\nnew run\n\n## Generated table\nnew rows\n")
    text = path.read_text()
    assert "old run" not in text and "old rows" not in text
    assert text.index("new rows") < text.index("## A finding (another CPU)\nkept text")
    assert text.count("## Generated table") == 1


def test_first_write_and_no_sections(tmp_path):
    records = _records()
    path = tmp_path / "new.md"
    records.write_record(path, "# Title\n\nrun\n")
    assert path.read_text() == "# Title\n\nrun\n"
    assert records.kept_sections("# Title\n\nonly a run\n", "# Title\n") == ""
