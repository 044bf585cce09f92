#!/usr/bin/env bash
# Writes a lock (pip constraints: exact versions of every package) for one venv of the project.
# Usage: scripts/lock.sh PYTHON "TORCH_SPEC..." "[extras]" OUTPUT
# A throwaway venv gets torch first (pinned: an unpinned torch is a CUDA build), then the project with
# its extras at the newest releases pyproject.toml's ranges allow; `pip freeze` of it is the lock.
set -euo pipefail
python=$1; torch=$2; extras=$3; output=$4
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
"$python" -m venv "$work/venv"
# shellcheck disable=SC2086  # the torch spec may name several packages
"$work/venv/bin/pip" install -q $torch
"$work/venv/bin/pip" install -q --upgrade -e ".$extras"
mkdir -p "$(dirname "$output")"
{
  echo "# Exact versions for: pip install -c $output $torch; pip install -c $output -e \".$extras\""
  echo "# Written by \`make lock\` on $(date -u +%Y-%m-%d) with $("$python" --version 2>&1); refresh with \`make lock\`."
  # torch's local version (+cpu) is left out: the pin then takes whichever build lies on disk.
  "$work/venv/bin/pip" freeze --exclude-editable | sed -E 's/^(torch(vision)?==[^+]+)\+.*/\1/'
} > "$output.tmp"
mv "$output.tmp" "$output"
echo "wrote $output ($(grep -vc '^#' "$output") packages)"
