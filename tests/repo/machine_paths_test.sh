#!/usr/bin/env bash
# Keeps the absolute paths of one machine out of the repository's docs/,
# scripts/, tools/, deploy/, bench/ and README.md: reports, notes and scripts name
# data by repository-relative paths (../shared/data/..., ../data-mr/...;
# scripts/eval*.sh and tools/eval/*.py write them so).
#
#   bash tests/repo/machine_paths_test.sh [ROOT]
#
# ROOT (default: the checkout holding this script, wherever it is) is read
# with `git ls-files` when it is the top of a git checkout, else (a source
# tarball, a scratch copy) every file under those folders. Text files only
# (grep -I); a symbolic link's target is checked as a line of its own.
# Prints FILE:LINE: PATH for each offending path; exit 1 if any, else 0.
#
# What counts as a path of one machine: an absolute path (at the start of a
# line or after a character that cannot end a relative path or a URL's
# host: not a letter, digit, `_ . ~ $ } ) ]`) that is
#   /work, /work/...        the working folders of a build machine
#   /root, /root/...        root's home; allowed in deploy/**/Dockerfile*
#                           and Containerfile* (the image's own file system)
#   /home/NAME, /Users/NAME, /mnt/NAME, /media/NAME
#   /var/tmp/NAME           unless NAME begins with `interslice` or `orthanc`
#                           (README.md's and docs/'s documented examples:
#                           --spool /var/tmp/interslice, /var/tmp/orthanc-db)
#   X:\... or X:/...        a Windows drive
# Not: system paths (/usr, /etc, /var/lib/interslice, /proc, /dev), /tmp
# (examples), /opt, /srv, container paths (/src, /out), URLs' paths
# (https://host/work/...: preceded by the host), relative paths
# (../shared/data, build-eval/work/...).
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
root="$(cd "${1:-$here/../..}" && pwd)"
areas=(docs scripts tools deploy bench README.md)

# The candidates as one extended regular expression: each match starts with
# the character before the path (none at a line start); /work and /root
# match with any name that begins so (/workspace), offends() keeps the
# exact ones and applies the exemptions.
pc='[^][:space:]"'"'"'`<>|;,(){}*]'   # a character of a path
re="(^|[^]A-Za-z0-9_.~\$})])("
re+="/(work|root)$pc*"
re+="|/(home|Users|mnt|media)/[A-Za-z0-9_.-]$pc*"
re+="|/var/tmp/$pc+"
re+="|[A-Za-z]:(\\\\{1,2}|/)[A-Za-z0-9_.\$-]$pc*"
re+=")"

list_files() {
  local top
  top="$(git -C "$root" rev-parse --show-toplevel 2>/dev/null || true)"
  if [[ -n $top && "$(cd "$top" && pwd -P)" == "$(pwd -P)" ]]; then
    git -C "$root" ls-files -z -- "${areas[@]}"
  else
    local a existing=()
    for a in "${areas[@]}"; do [[ -e $a ]] && existing+=("$a"); done
    [[ ${#existing[@]} -gt 0 ]] && find "${existing[@]}" \( -type f -o -type l \) -print0
  fi
}

# FILE MATCH: prints the path and succeeds when the match breaks a rule.
offends() {
  local file="$1" path="$2"
  path="${path#[!/A-Za-z]}"   # the character before the path
  path="${path%[.:]}"         # a sentence's full stop
  case "$path" in
    /work|/work/*) ;;
    /root|/root/*)
      case "$file" in
        deploy/*Dockerfile*|deploy/*Containerfile*) return 1 ;;
      esac ;;
    /work*|/root*) return 1 ;;   # /workspace, /rootfs: another name
    /var/tmp/interslice*|/var/tmp/orthanc*) return 1 ;;
  esac
  printf '%s\n' "$path"
}

cd "$root"
hits=0
checked=0
while IFS= read -r -d '' file; do
  if [[ -L $file ]]; then
    checked=$((checked + 1))
    target="$(readlink "$file")"
    while IFS= read -r m; do
      if p="$(offends "$file" "$m")"; then
        echo "$file: symbolic link to $p"
        hits=$((hits + 1))
      fi
    done < <(printf '%s\n' "$target" | grep -oE "$re" || true)
    continue
  fi
  [[ -f $file ]] || continue   # deleted in the working tree, not yet in git
  checked=$((checked + 1))
  while IFS= read -r hit; do
    line="${hit%%:*}"
    m="${hit#*:}"
    if p="$(offends "$file" "$m")"; then
      echo "$file:$line: $p"
      hits=$((hits + 1))
    fi
  done < <(grep -noIE "$re" -- "$file" || true)
done < <(list_files)

if [[ $checked -eq 0 ]]; then
  echo "machine_paths_test: no file of ${areas[*]} found under $root" >&2
  exit 1
fi
if [[ $hits -gt 0 ]]; then
  echo "machine_paths_test: $hits absolute path(s) of one machine in $checked files under $root" \
       "(write them relative to the repository root, e.g. ../shared/data/...)" >&2
  exit 1
fi
echo "machine_paths_test: $checked files of ${areas[*]}: no absolute path of one machine"
