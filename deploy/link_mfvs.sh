#!/usr/bin/env bash
# link_mfvs.sh BIN_DIR TARGET: put the `mfvs` command in BIN_DIR as a link to TARGET (a checkout's .venv/bin/mfvs).
# A link to another checkout (or to one that is gone) is replaced, saying which; a file that is not a link is left
# alone. deploy/install.sh calls it.
set -euo pipefail
bin_dir=$1
target=$2
link="$bin_dir/mfvs"
mkdir -p "$bin_dir"
if [[ -L "$link" ]]; then
    previous=$(readlink "$link")
    if [[ "$previous" != "$target" ]]; then
        state="a checkout that is gone"
        [[ -e "$previous" ]] && state="another checkout"
        echo "replacing $link -> $previous ($state) with -> $target"
    fi
elif [[ -e "$link" ]]; then
    echo "$link exists and is not a link: left alone (run mfvs as $target, or set MFVS_BIN_DIR)" >&2
    exit 0
fi
ln -sfn "$target" "$link"
echo "mfvs is at $link -> $target"
