"""tools/case_table.py: every case run as a user runs it, its summary tabulated."""
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(__file__)), "tools"))
import case_table  # noqa: E402


def test_two_cases_run_and_are_tabulated(tmp_path, capsys):
    out = tmp_path / "table.md"
    rc = case_table.main(["--cases", "euler,helix", "--workdir", str(tmp_path / "runs"),
                          "--out", str(out)])
    assert rc == 0
    text = out.read_text()
    rows = {l.split("|")[1].strip(): [c.strip() for c in l.split("|")[1:-1]]
            for l in text.splitlines() if l.startswith("| ") and "case" not in l}
    euler, helix = rows["euler"], rows["helix"]
    assert euler[1] == "minimize" and int(euler[2]) >= 1 and int(euler[3]) >= int(euler[2])
    assert euler[5] == "yes" and euler[6] == "converged (exit 0)"
    assert helix[5] == "not counted" and helix[6] == "converged (exit 0)"
    assert "cores" in text.splitlines()[0]


def test_stability_column():
    steps = lambda *n: {"steps": [{"negative_eigenvalues": k} for k in n]}  # noqa: E731
    assert case_table.stability(steps(0, 0)) == "yes"
    assert case_table.stability(steps(0, 2, 1)) == "no (2 of 3 steps unstable)"
    assert case_table.stability(steps(0, None)) == "not counted"
    assert case_table.stability({}) == "not counted"


def test_a_case_that_does_not_run_says_so(tmp_path):
    row = case_table.run_case("no_such_case", str(tmp_path), 1, 60)
    assert row["end"].startswith("no summary (exit 2")
    assert case_table.main(["--cases", "no_such_case", "--workdir", str(tmp_path)]) == 1
