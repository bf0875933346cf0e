# Shared set-up for the example pipelines (sourced, not run).
#
# - REPO: the checkout holding these scripts.
# - Makes `leangate` findable: when gst-inspect-1.0 cannot find it, prepends the repository's
#   target/release and target/debug to GST_PLUGIN_PATH; fails with a clear message if the
#   plugin is still missing (build it with `cargo build`).
# - MODEL / MODEL_PROP: the model file, from $LEANGATE_MODEL, and the one pipeline word that sets
#   it (quoted with gst_quote). Empty means the element's default: the student embedded in the
#   plugin (leangate-s).
# - gst_quote VALUE: VALUE as a gst-launch property value (in double quotes, `\` and `"` escaped),
#   so that a path with spaces, quotes or backslashes reaches the element as it is.

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"

leangate_require_plugin() {
    if ! command -v gst-launch-1.0 >/dev/null 2>&1; then
        echo "error: gst-launch-1.0 not found (apt install gstreamer1.0-tools)" >&2
        exit 2
    fi
    if ! gst-inspect-1.0 leangate >/dev/null 2>&1; then
        local d
        for d in "$REPO/target/debug" "$REPO/target/release"; do
            if [ -e "$d/libgstleangate.so" ]; then
                export GST_PLUGIN_PATH="$d${GST_PLUGIN_PATH:+:$GST_PLUGIN_PATH}"
            fi
        done
        if ! gst-inspect-1.0 leangate >/dev/null 2>&1; then
            echo "error: GStreamer element 'leangate' not found. Build it (cd $REPO && cargo build)" \
                 "and set GST_PLUGIN_PATH=$REPO/target/debug" >&2
            exit 2
        fi
    fi
}

gst_quote() {
    local v=${1//\\/\\\\}
    v=${v//\"/\\\"}
    printf '"%s"' "$v"
}

MODEL="${LEANGATE_MODEL:-}"
if [ -n "$MODEL" ]; then
    if [ ! -f "$MODEL" ]; then
        echo "error: model not found: $MODEL" >&2
        exit 2
    fi
    MODEL_PROP="model=$(gst_quote "$MODEL")"
else
    MODEL_PROP=""
fi

# Print the frames in/kept figures from `gst-launch-1.0 -m` output on stdin (the element's
# `leangate-stats` message, posted at EOS), passing every line through. Ctrl-C reaches the whole
# foreground group: this reader ignores it, so that gst-launch can finish (-e: EOS, the final
# statistics) and its last lines still get through.
leangate_summarise() (
    trap '' INT
    awk '
        { print }
        /leangate-stats/ {
            stats = $0
        }
        END {
            if (stats == "") { print "summary: no leangate-stats message (did the pipeline reach EOS?)"; exit }
            n = split("frames-in frames-kept keep-ratio inference-mean-us inference-p99-us execution-provider threshold", k, " ")
            line = "summary:"
            for (i = 1; i <= n; i++) {
                if (match(stats, k[i] "=\\([a-z0-9]+\\)[^,;]*")) {
                    v = substr(stats, RSTART, RLENGTH)
                    typed = (v ~ /=\(double\)/)
                    sub(/=\([a-z0-9]+\)/, "=", v)
                    # A double as GStreamer serialises it (0.40000000000000002): as the user gave it.
                    if (typed) { eq = index(v, "="); v = substr(v, 1, eq) sprintf("%.6g", substr(v, eq + 1) + 0) }
                    line = line " " v
                }
            }
            print line
        }'
)
