"""tools/bench_kernels.py: every row measured at a small size, the planar scene's kernels and
the two LUs of its in-plane Jacobian."""
from conftest import load_tool


def test_the_kernel_bench_measures_every_row(capsys):
    bench = load_tool("bench_kernels")
    assert bench.main(["--sizes", "20", "--repeat", "1"]) == 0
    out = capsys.readouterr().out
    for name in ("plane tangent (lanes 2)", "3-D tangent", "residual", "energy",
                 "plane tangents into J", "in-plane Jacobian",
                 "chain LU factor", "chain LU solve", "PETSc LU factor", "PETSc LU solve"):
        row = next(line for line in out.splitlines() if line.startswith(f"| {name}"))
        fastest = float(row.split("|")[3])
        assert fastest > 0.0, row
