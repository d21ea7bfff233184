#!/usr/bin/env bash
# Run a command under mpirun so that only rank 0 prints; other ranks log to a file
# (shown when they fail, so a failure on rank 1 is never silent).
rank="${OMPI_COMM_WORLD_RANK:-${PMI_RANK:-0}}"
if [ "$rank" = 0 ]; then exec "$@"; fi
log="${TMPDIR:-/tmp}/rodsnes_rank${rank}_$$.log"
"$@" >"$log" 2>&1
rc=$?
if [ $rc != 0 ]; then echo "---- rank $rank failed (rc=$rc): tail of $log ----" >&2; tail -n 60 "$log" >&2; fi
exit $rc
