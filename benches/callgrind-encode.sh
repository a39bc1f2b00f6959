#!/bin/sh
# Instructions per code (callgrind Ir) of the dispatched batch pipeline `Encoder::encode_batch`
# and of the streaming baseline `emc_cpu::encode::stream_baseline`, each collected only inside
# its own function (--toggle-collect), on `emc layout --ratios --rounds 1`, which calls each
# kernel twice (warm-up and one round) on PRIMS boxes of builtin:uniform.
#
# Usage (from the workspace root): benches/callgrind-encode.sh [LAYOUT ...]
#   environment: PRIMS (default 1048576)
set -eu
prims=${PRIMS:-1048576}
[ $# -gt 0 ] || set -- morton63 emc64-var emc64-sort emc32-var
cargo build --release -p emc-cpu >/dev/null
dir=$(mktemp -d)
trap 'rm -rf "$dir"' EXIT
count() { # $1 = function to collect in, $2 = layout
    valgrind --tool=callgrind --callgrind-out-file="$dir/cg.out" --toggle-collect="$1" \
        target/release/emc layout --ratios --rounds 1 --prims "$prims" --layout "$2" \
        >"$dir/log" 2>"$dir/err" || { cat "$dir/err" >&2; exit 1; }
    callgrind_annotate "$dir/cg.out" | awk '/PROGRAM TOTALS/ { gsub(",", "", $1); print $1 }'
}
for layout in "$@"; do
    pipe=$(count 'emc_core::encoder::Encoder::encode_batch' "$layout")
    base=$(count 'emc_cpu::encode::stream_baseline' "$layout")
    awk -v l="$layout" -v p="$pipe" -v b="$base" -v n="$prims" 'BEGIN {
        printf "%-12s pipeline %6.2f instr/code   baseline %5.2f instr/code   (%d codes x 2 calls)\n",
            l, p / (2 * n), b / (2 * n), n }'
done
