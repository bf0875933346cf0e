#!/usr/bin/env bash
# Install LeanGate under $PREFIX (`make install`), or remove it (`--uninstall`, `make uninstall`):
#   $PREFIX/lib/gstreamer-1.0/libgstleangate.so    the plugin
#   $PREFIX/lib/leangate/libonnxruntime.so*         ONNX Runtime, found by the plugin relative to
#                                                   itself (../leangate/), and by the CLI (../lib/leangate/)
#   $PREFIX/lib/leangate/python/leangate_client     the Python client (pip --no-deps --target)
#   $PREFIX/bin/leangate, $PREFIX/bin/leangate-client
#   $GST_LINK_DIR/libgstleangate.so                 a symlink to the plugin in a directory GStreamer
#                                                   scans with no variables set (see below)
# GST_LINK_DIR: `auto` (the default) is the user's plugin directory
# ($XDG_DATA_HOME/gstreamer-1.0/plugins, i.e. ~/.local/share/gstreamer-1.0/plugins) when $PREFIX is
# under $HOME, else the system's (`pkg-config --variable=pluginsdir gstreamer-1.0`,
# /usr/lib/x86_64-linux-gnu/gstreamer-1.0 on Debian); empty: no link (then set
# GST_PLUGIN_PATH=$PREFIX/lib/gstreamer-1.0). PLUGIN, CLI, ORT_DIR and PYTHON select what is
# installed (the tests install debug builds into a temporary prefix).
set -euo pipefail
cd "$(dirname "$0")/.."

PREFIX=${PREFIX:-$HOME/.local}
PLUGIN=${PLUGIN:-target/release/libgstleangate.so}
CLI=${CLI:-target/release/leangate}
ORT_DIR=${ORT_DIR:-.deps/onnxruntime}
PYTHON=${PYTHON:-/usr/bin/python3}
GST_LINK_DIR=${GST_LINK_DIR-auto}

case "$PREFIX" in
  /*) ;;
  *) echo "install: PREFIX must be an absolute path, got '$PREFIX'" >&2; exit 2 ;;
esac
PREFIX=${PREFIX%/}
if [ "$GST_LINK_DIR" = auto ]; then
  case "$PREFIX/" in
    "${HOME%/}"/*) GST_LINK_DIR=${XDG_DATA_HOME:-$HOME/.local/share}/gstreamer-1.0/plugins ;;
    *) GST_LINK_DIR=$(pkg-config --variable=pluginsdir gstreamer-1.0) ;;
  esac
fi

PLUGIN_DIR=$PREFIX/lib/gstreamer-1.0
LIB_DIR=$PREFIX/lib/leangate
BIN_DIR=$PREFIX/bin
INSTALLED_PLUGIN=$PLUGIN_DIR/libgstleangate.so

remove_link() {
  local link=$GST_LINK_DIR/libgstleangate.so
  if [ -n "$GST_LINK_DIR" ] && [ -L "$link" ] && [ "$(readlink "$link")" = "$INSTALLED_PLUGIN" ]; then
    rm -f "$link"
    echo "uninstall: removed the link $link"
  fi
}

if [ "${1:-}" = --uninstall ]; then
  remove_link
  rm -f "$INSTALLED_PLUGIN" "$BIN_DIR/leangate" "$BIN_DIR/leangate-client"
  rm -rf "$LIB_DIR"
  rmdir "$PLUGIN_DIR" 2>/dev/null || true
  echo "uninstall: removed LeanGate from $PREFIX"
  exit 0
fi

for f in "$PLUGIN" "$CLI" "$ORT_DIR/libonnxruntime.so"; do
  [ -e "$f" ] || { echo "install: $f is missing (run \`make release\` and \`make setup\` first)" >&2; exit 1; }
done

mkdir -p "$PLUGIN_DIR" "$LIB_DIR" "$BIN_DIR"
install -m 755 "$PLUGIN" "$INSTALLED_PLUGIN"
install -m 755 "$CLI" "$BIN_DIR/leangate"
# The library, its version-named file and the providers' helpers, symlinks kept.
cp -P "$ORT_DIR"/libonnxruntime*.so* "$LIB_DIR/"

# leangate-client: pip from a copy of pipelines/ (an in-tree build would leave build/ and
# *.egg-info in the checkout); no dependencies (PyGObject and numpy come from the system).
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
cp -r pipelines/pyproject.toml pipelines/README.md pipelines/leangate_client "$tmp/"
rm -rf "$LIB_DIR/python"
"$PYTHON" -m pip install -q --disable-pip-version-check --no-deps --no-build-isolation \
  --no-compile --target "$LIB_DIR/python" "$tmp" >/dev/null
rm -rf "$LIB_DIR/python/bin"
cat >"$BIN_DIR/leangate-client" <<EOF
#!/bin/sh
# leangate-client, installed by LeanGate's \`make install\`: the Python client on $PYTHON.
here=\$(dirname "\$(readlink -f "\$0")")
PYTHONPATH="\$here/../lib/leangate/python\${PYTHONPATH:+:\$PYTHONPATH}" exec $PYTHON -m leangate_client "\$@"
EOF
chmod 755 "$BIN_DIR/leangate-client"

if [ -n "$GST_LINK_DIR" ]; then
  mkdir -p "$GST_LINK_DIR"
  if [ "$(readlink -f "$GST_LINK_DIR")" != "$(readlink -f "$PLUGIN_DIR")" ]; then
    ln -sfn "$INSTALLED_PLUGIN" "$GST_LINK_DIR/libgstleangate.so"
    echo "install: linked $GST_LINK_DIR/libgstleangate.so (a directory GStreamer scans)"
  fi
else
  echo "install: no link made; set GST_PLUGIN_PATH=$PLUGIN_DIR for GStreamer to find the plugin"
fi
echo "install: LeanGate in $PREFIX (plugin $INSTALLED_PLUGIN, ONNX Runtime in $LIB_DIR, $BIN_DIR/leangate and $BIN_DIR/leangate-client)"
