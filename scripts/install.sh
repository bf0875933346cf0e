#!/usr/bin/env bash
# Install LeanGate under $PREFIX (`make install`), or remove it (`--uninstall`, `make uninstall`).
# It only copies what `make release` built (run that first, as yourself; then `sudo make install`
# needs no Rust toolchain, network or HOME):
#   $PREFIX/lib/gstreamer-1.0/libgstleangate.so    the plugin
#   $PREFIX/lib/leangate/libonnxruntime.so*         ONNX Runtime, found by the plugin relative to
#                                                   itself (../leangate/), and by the CLI (../lib/leangate/)
#   $PREFIX/lib/leangate/python/leangate_client     the Python client (pip --no-deps --target)
#   $PREFIX/lib/leangate/python/reconstruct.py      the consumer the installed `leangate eval
#                                                   --reconstruct` runs (pipelines/reconstruct.py)
#   $PREFIX/bin/leangate, $PREFIX/bin/leangate-client
#   $PREFIX/share/doc/leangate/models/README.md     the model card (the ONNX contract)
#   $PREFIX/lib/leangate/install-manifest           what this install wrote (below)
#   $GST_LINK_DIR/libgstleangate.so                 a symlink to the plugin in a directory GStreamer
#                                                   scans with no variables set (see below)
# GST_LINK_DIR: `auto` (the default) links only for the two standard prefixes: ~/.local (into
# $XDG_DATA_HOME/gstreamer-1.0/plugins, i.e. ~/.local/share/gstreamer-1.0/plugins) and /usr/local
# (into the system's `pkg-config --variable=pluginsdir gstreamer-1.0`,
# /usr/lib/x86_64-linux-gnu/gstreamer-1.0 on Debian). Any other PREFIX gets no link (nothing is
# written outside it; set GST_PLUGIN_PATH=$PREFIX/lib/gstreamer-1.0), unless GST_LINK_DIR names a
# directory. Empty: no link. A file, or a link not pointing at this install's plugin, already at
# the link's path is left alone and the install refused.
#
# The manifest lists, one per line, tab-separated: `dir PATH` (a directory this install created),
# `file SHA256 PATH`, `link TARGET PATH`. Uninstall removes exactly those entries, each only while
# it is still what install wrote (same checksum, same link target), directories only when empty
# (Python's __pycache__ of our modules aside); directories that existed before are kept, but for
# LeanGate's own ($PREFIX/lib/leangate, $PREFIX/share/doc/leangate and below). PREFIX
# may be spelled differently (`~/.local//`, `..` segments): it is normalised (realpath) both ways.
# The install is staged in a temporary directory, then moved into place; if a step fails, what it
# did is undone (files it replaced restored) and nothing of it is left.
#
# PLUGIN, CLI, ORT_DIR and PYTHON select what is installed (the tests install debug builds into a
# temporary prefix); relative paths are relative to the checkout.
set -euo pipefail
cd "$(dirname "$0")/.."

MODE=install
[ "${1:-}" = --uninstall ] && MODE=uninstall
MANIFEST_HEADER="# LeanGate install manifest (scripts/install.sh): what \`make install\` wrote; \`make uninstall\` removes exactly these entries"

say() { echo "$MODE: $*"; }
warn() { echo "$MODE: $*" >&2; }
die() {
  warn "$*"
  exit 1
}

# A path without a tab or newline (the manifest's separators), absolute or ~/..., normalised.
normal_path() { # NAME VALUE
  local v=$2
  case "$v" in
    "~") v=${HOME:-} ;;
    "~/"*) v=${HOME:-}/${v#"~/"} ;;
  esac
  case "$v" in
    *$'\t'* | *$'\n'*) warn "$1 must not contain a tab or a newline"; exit 2 ;;
    /*) ;;
    *) warn "$1 must be an absolute path (or ~/...), got '$2'"; exit 2 ;;
  esac
  realpath -m -- "$v"
}

PREFIX=$(normal_path PREFIX "${PREFIX:-${HOME:-}/.local}")
[ "$PREFIX" != / ] || { warn "PREFIX=/ is not supported (use /usr/local)"; exit 2; }
# One install or uninstall at a time per prefix: an exclusive lock on the prefix (or, while it
# does not exist yet, on its nearest existing parent) held for the whole run. A lock on a
# directory writes no file.
lock_dir=$PREFIX
while [ ! -d "$lock_dir" ]; do lock_dir=$(dirname -- "$lock_dir"); done
if command -v flock >/dev/null; then
  exec 9<"$lock_dir"
  flock -w 600 9 || { warn "another LeanGate install or uninstall holds $lock_dir; try again"; exit 1; }
fi
PLUGIN_DIR=$PREFIX/lib/gstreamer-1.0
LIB_DIR=$PREFIX/lib/leangate
BIN_DIR=$PREFIX/bin
INSTALLED_PLUGIN=$PLUGIN_DIR/libgstleangate.so
MANIFEST=$LIB_DIR/install-manifest

sha() { sha256sum <"$1" | cut -d' ' -f1; }
exists() { [ -e "$1" ] || [ -L "$1" ]; }

REMOVED=0
# Remove one manifest entry (KIND A PATH) if it is still what install wrote; else keep it, saying so.
remove_entry() {
  local kind=$1 a=$2 path=$3
  exists "$path" || return 0
  case "$kind" in
    file)
      if [ -f "$path" ] && [ ! -L "$path" ] && [ "$(sha "$path")" = "$a" ]; then
        rm -f -- "$path" && REMOVED=$((REMOVED + 1))
      else
        warn "kept $path: changed since LeanGate installed it"
      fi
      ;;
    link)
      if [ -L "$path" ] && [ "$(readlink -- "$path")" = "$a" ]; then
        rm -f -- "$path" && REMOVED=$((REMOVED + 1))
      else
        warn "kept $path: no longer the link LeanGate made"
      fi
      ;;
  esac
}

# Remove a directory install created once it is empty (a __pycache__ of .pyc files aside).
remove_dir() {
  local d=$1
  [ -d "$d" ] && [ ! -L "$d" ] || return 0
  if [ "$(ls -A -- "$d")" = __pycache__ ] && [ -z "$(find "$d/__pycache__" -mindepth 1 ! \( -type f -name '*.pyc' \) -print -quit)" ]; then
    rm -rf -- "$d/__pycache__"
  fi
  if rmdir -- "$d" 2>/dev/null; then
    REMOVED=$((REMOVED + 1))
  else
    warn "kept $d: not empty"
  fi
}

# The entries of a manifest, as `KIND<TAB>A<TAB>PATH` (A is - for a directory).
read_manifest() {
  local kind a b
  head -n1 -- "$1" | grep -qxF "$MANIFEST_HEADER" || die "$1 is not a LeanGate install manifest; nothing done"
  while IFS=$'\t' read -r kind a b; do
    case "$kind" in
      dir) printf 'dir\t-\t%s\n' "$a" ;;
      file | link) printf '%s\t%s\t%s\n' "$kind" "$a" "$b" ;;
    esac
  done < <(tail -n +2 -- "$1")
}

if [ "$MODE" = uninstall ]; then
  if [ ! -f "$MANIFEST" ]; then
    say "nothing installed in $PREFIX (no install manifest $MANIFEST); nothing removed"
    if exists "$INSTALLED_PLUGIN"; then
      warn "$INSTALLED_PLUGIN is there, from an install made before LeanGate wrote a manifest: run \`make install PREFIX=$PREFIX\` over it, then \`make uninstall PREFIX=$PREFIX\`"
    fi
    exit 0
  fi
  entries=$(read_manifest "$MANIFEST")
  while IFS=$'\t' read -r kind a path; do
    [ "$kind" = dir ] || remove_entry "$kind" "$a" "$path"
  done <<<"$entries"
  rm -f -- "$MANIFEST"
  while IFS= read -r d; do
    remove_dir "$d"
  done < <(awk -F'\t' '$1 == "dir" { print $3 }' <<<"$entries" | LC_ALL=C sort -r)
  say "removed LeanGate from $PREFIX ($REMOVED entries of its install manifest)"
  exit 0
fi

# ---- install ----

PLUGIN=${PLUGIN:-target/release/libgstleangate.so}
CLI=${CLI:-target/release/leangate}
ORT_DIR=${ORT_DIR:-.deps/onnxruntime}
PYTHON=${PYTHON:-/usr/bin/python3}
GST_LINK_DIR=${GST_LINK_DIR-auto}

for f in "$PLUGIN" "$CLI" "$ORT_DIR/libonnxruntime.so"; do
  [ -e "$f" ] || die "$f is missing: run \`make release\` first (as yourself; it builds the plugin and the CLI and fetches ONNX Runtime), then \`make install\` only copies"
done

link_note=""
if [ "$GST_LINK_DIR" = auto ]; then
  data_home=${XDG_DATA_HOME:-}
  case "$data_home" in /*) ;; *) data_home=${HOME:-}/.local/share ;; esac
  if [ -n "${HOME:-}" ] && [ "$PREFIX" = "$(realpath -m -- "$HOME/.local")" ]; then
    GST_LINK_DIR=$data_home/gstreamer-1.0/plugins
  elif [ "$PREFIX" = /usr/local ]; then
    GST_LINK_DIR=$(pkg-config --variable=pluginsdir gstreamer-1.0 2>/dev/null) ||
      die "pkg-config cannot name GStreamer's plugin directory (apt install libgstreamer1.0-dev); set GST_LINK_DIR (or GST_LINK_DIR= for no link)"
  else
    GST_LINK_DIR=""
    link_note="no link made outside $PREFIX (only ~/.local and /usr/local get one; GST_LINK_DIR=DIR links into DIR)"
  fi
fi
LINK=""
if [ -n "$GST_LINK_DIR" ]; then
  GST_LINK_DIR=$(normal_path GST_LINK_DIR "$GST_LINK_DIR")
  if [ "$GST_LINK_DIR" = "$PLUGIN_DIR" ]; then
    link_note="no link needed (GST_LINK_DIR is the plugin's own directory)"
  else
    LINK=$GST_LINK_DIR/libgstleangate.so
    if [ -L "$LINK" ]; then
      target=$(readlink -- "$LINK")
      [ "$target" = "$INSTALLED_PLUGIN" ] ||
        die "refusing to install: $LINK is a link to $target, not to $INSTALLED_PLUGIN; it is left as it is. Remove it (\`make uninstall PREFIX=...\` of the install it belongs to), or install with GST_LINK_DIR= (no link)"
    elif exists "$LINK"; then
      die "refusing to install: $LINK exists and is not a link LeanGate made; it is left as it is. Remove it, or install with GST_LINK_DIR= (no link; then GST_PLUGIN_PATH=$PLUGIN_DIR)"
    fi
  fi
elif [ -z "$link_note" ]; then
  link_note="no link made (GST_LINK_DIR is empty)"
fi

# Stage everything in a temporary directory: $stage mirrors $PREFIX.
tmp=$(mktemp -d)
STATE=staging
PLACED=()
BACKUPS=()
CREATED=()
OWN=() # LeanGate's own directories, created now or before (by an install without a manifest)
rollback() {
  local i
  for ((i = ${#PLACED[@]} - 1; i >= 0; i--)); do rm -f -- "${PLACED[i]}"; done
  # (A backup is recorded before its rename: one that an interrupt kept from happening is not there.)
  for ((i = ${#BACKUPS[@]} - 1; i >= 0; i--)); do
    if exists "${BACKUPS[i]}.leangate-old.$$"; then mv -fT -- "${BACKUPS[i]}.leangate-old.$$" "${BACKUPS[i]}"; fi
  done
  for ((i = ${#CREATED[@]} - 1; i >= 0; i--)); do rmdir -- "${CREATED[i]}" 2>/dev/null || true; done
  warn "failed: undone, nothing of this install is left (what it replaced is restored)"
}
on_exit() {
  local rc=$?
  trap '' INT TERM HUP # a second Ctrl-C must not cut the rollback short
  if [ "$STATE" = placing ] && [ "$rc" != 0 ]; then rollback; fi
  rm -rf -- "$tmp"
  exit "$rc"
}
trap on_exit EXIT
trap 'exit 130' INT TERM HUP

stage=$tmp/stage
mkdir -p "$stage/lib/gstreamer-1.0" "$stage/lib/leangate" "$stage/bin" "$stage/share/doc/leangate/models"
install -m 755 "$PLUGIN" "$stage/lib/gstreamer-1.0/libgstleangate.so"
install -m 755 "$CLI" "$stage/bin/leangate"
# The library, its version-named file and the providers' helpers, symlinks kept.
cp -P "$ORT_DIR"/libonnxruntime*.so* "$stage/lib/leangate/"
install -m 644 models/README.md "$stage/share/doc/leangate/models/README.md"
# leangate-client: pip from a copy of pipelines/ (an in-tree build would leave build/ and
# *.egg-info in the checkout); no dependencies (PyGObject and numpy come from the system).
mkdir "$tmp/src"
cp -r pipelines/pyproject.toml pipelines/README.md pipelines/leangate_client "$tmp/src/"
PATH=/usr/local/bin:/usr/bin:/bin "$PYTHON" -m pip install -q --disable-pip-version-check --root-user-action=ignore --no-deps --no-build-isolation \
  --no-compile --target "$stage/lib/leangate/python" "$tmp/src" >/dev/null ||
  die "pip could not install the Python client with $PYTHON (apt install python3-pip)"
rm -rf "$stage/lib/leangate/python/bin"
# The reconstruction consumer `leangate eval --reconstruct` runs: beside the package it imports.
install -m 644 pipelines/reconstruct.py "$stage/lib/leangate/python/reconstruct.py"
cat >"$stage/bin/leangate-client" <<EOF
#!/bin/sh
# leangate-client, installed by LeanGate's \`make install\`: the Python client on $PYTHON.
here=\$(dirname "\$(readlink -f "\$0")")
PYTHONPATH="\$here/../lib/leangate/python\${PYTHONPATH:+:\$PYTHONPATH}" exec $(printf %q "$PYTHON") -m leangate_client "\$@"
EOF
chmod 755 "$stage/bin/leangate-client"

# What an earlier install wrote (replaced now, or removed after this one if it is not rewritten).
old_entries=""
if [ -f "$MANIFEST" ]; then
  old_entries=$(read_manifest "$MANIFEST")
fi

# Put the staged tree in place, recording each step for the rollback.
err=$tmp/err
mkdirs() {
  local d=$1
  [ -d "$d" ] && return 0
  if exists "$d"; then die "cannot create the directory $d: a file is in the way"; fi
  mkdirs "$(dirname -- "$d")"
  mkdir -- "$d" 2>"$err" || die "cannot create the directory $d: $(cat "$err")"
  CREATED+=("$d")
}
place() { # SRC DEST (a file, or a symlink copied as one)
  local src=$1 dest=$2
  mkdirs "$(dirname -- "$dest")"
  if [ -d "$dest" ] && [ ! -L "$dest" ]; then die "cannot install $dest: a directory is in the way"; fi
  if exists "$dest"; then
    BACKUPS+=("$dest")
    mv -fT -- "$dest" "$dest.leangate-old.$$" 2>"$err" || die "cannot replace $dest: $(cat "$err")"
  fi
  PLACED+=("$dest")
  cp -P --preserve=mode -- "$src" "$dest" 2>"$err" || die "cannot write $dest: $(cat "$err")"
}

# Nothing of the user's is replaced: a file already where this install writes must be LeanGate's,
# from an earlier install (in its manifest, in LeanGate's own folders, or, for an install made
# before the manifest existed, recognisably LeanGate's own file). Checked before anything moves.
ours() { # DEST
  printf '%s\n' "$old_entries" | awk -F'\t' -v p="$1" '$3 == p {f = 1} END {exit !f}' && return 0
  case $1 in "$LIB_DIR"/* | "$PREFIX"/share/doc/leangate/*) return 0 ;; esac
  case $1 in
    */bin/leangate-client) grep -qs "installed by LeanGate" -- "$1" ;;
    */bin/leangate) grep -qsF "LeanGate: geometric-utility frame gating" -- "$1" ;;
    */libgstleangate.so) grep -qsF "GstLeanGate" -- "$1" ;;
    *) return 1 ;;
  esac
}
theirs=()
while IFS= read -r -d '' rel; do
  dest=$PREFIX/$rel
  if [ ! -d "$stage/$rel" ] && exists "$dest" && ! ours "$dest"; then theirs+=("$dest"); fi
done < <(cd "$stage" && find lib/leangate lib/gstreamer-1.0 share bin -print0)
if ((${#theirs[@]})); then
  die "refusing to install: ${theirs[*]} $([ ${#theirs[@]} = 1 ] && echo is || echo are) not from a LeanGate install and would be replaced; move $([ ${#theirs[@]} = 1 ] && echo it || echo them) away, or install into another PREFIX"
fi

declare -A NEW=()
entries=()
STATE=placing
mkdirs "$PREFIX"
# ONNX Runtime before the plugin that needs it; bin/ and the link last.
while IFS= read -r -d '' rel; do
  src=$stage/$rel dest=$PREFIX/$rel
  if [ -d "$src" ] && [ ! -L "$src" ]; then
    mkdirs "$dest"
    case "$rel" in lib/leangate* | share/doc/leangate*) OWN+=("$dest") ;; esac
    continue
  fi
  place "$src" "$dest"
  NEW[$dest]=1
  if [ -L "$src" ]; then
    entries+=("$(printf 'link\t%s\t%s' "$(readlink -- "$src")" "$dest")")
  else
    entries+=("$(printf 'file\t%s\t%s' "$(sha "$src")" "$dest")")
  fi
done < <(cd "$stage" && find lib/leangate lib/gstreamer-1.0 share bin -print0)
if [ -n "$LINK" ]; then
  mkdirs "$GST_LINK_DIR"
  ln -s -- "$INSTALLED_PLUGIN" "$tmp/link"
  place "$tmp/link" "$LINK"
  NEW[$LINK]=1
  entries+=("$(printf 'link\t%s\t%s' "$INSTALLED_PLUGIN" "$LINK")")
fi

# The manifest: the directories an earlier install created (still there), this one's and
# LeanGate's own (lib/leangate, share/doc/leangate and below), then the files and links.
{
  echo "$MANIFEST_HEADER"
  declare -A seen=()
  while IFS=$'\t' read -r kind a path; do
    if [ "$kind" = dir ] && [ -d "$path" ] && [ -z "${seen[$path]:-}" ]; then
      seen[$path]=1
      printf 'dir\t%s\n' "$path"
    fi
  done <<<"$old_entries"
  for d in "${CREATED[@]}" "${OWN[@]}"; do
    if [ -z "${seen[$d]:-}" ]; then
      seen[$d]=1
      printf 'dir\t%s\n' "$d"
    fi
  done
  printf '%s\n' "${entries[@]}"
} >"$tmp/manifest"
place "$tmp/manifest" "$MANIFEST"
chmod 644 "$MANIFEST"

STATE=done
for b in "${BACKUPS[@]}"; do rm -f -- "$b.leangate-old.$$"; done
# What the earlier install wrote and this one did not: removed, if still as it was written.
while IFS=$'\t' read -r kind a path; do
  if [ "$kind" != dir ] && [ -n "$kind" ] && [ -z "${NEW[$path]:-}" ]; then
    remove_entry "$kind" "$a" "$path"
  fi
done <<<"$old_entries"

if [ -n "$LINK" ]; then
  say "linked $LINK (a directory GStreamer scans)"
elif [ "$GST_LINK_DIR" = "$PLUGIN_DIR" ]; then
  say "$link_note"
else
  say "$link_note; set GST_PLUGIN_PATH=$PLUGIN_DIR for GStreamer to find the plugin"
fi
say "LeanGate in $PREFIX (plugin $INSTALLED_PLUGIN, ONNX Runtime in $LIB_DIR, $BIN_DIR/leangate and $BIN_DIR/leangate-client, model card $PREFIX/share/doc/leangate/models/README.md); what was written is listed in $MANIFEST"
case ":$PATH:" in
  *":$BIN_DIR:"*) ;;
  *) say "$BIN_DIR is not on PATH: add it (export PATH=\"$BIN_DIR:\$PATH\") to run leangate and leangate-client by name" ;;
esac
