#!/usr/bin/env bash
# The fleet's signed apt repository of the robot's packages, by channel (reprepro and gpg):
#
#   deploy/apt/repo.sh init DIR               a repository with the channels stable and beta,
#                                             signed by DIR's own key (made here unless
#                                             NORI_APT_KEY names one in $GNUPGHOME)
#   deploy/apt/repo.sh publish DIR DEB...     packages into beta (the only way in)
#   deploy/apt/repo.sh promote DIR VERSION    beta's packages of VERSION into stable (the only
#                                             way there: stable gets what ran on beta)
#   deploy/apt/repo.sh list DIR               what each channel holds
#   deploy/apt/repo.sh sources URL CHANNEL    a robot's /etc/nori/fleet-repository.sources
#   deploy/apt/repo.sh serve DIR LISTEN       DIR/public over HTTP with nginx (foreground), as
#                                             the fleet's web server would (deploy/README.md)
#
# What robots fetch is DIR/public (dists/, pool/, and the key robots trust,
# nori-archive-keyring.gpg); DIR/conf, DIR/db and DIR/gnupg stay on the fleet's side. Every
# channel's Release is signed (InRelease and Release.gpg): a robot's apt refuses an index or a
# package that does not match it. Needs reprepro, gpg and nginx (installed when missing).
set -euo pipefail
usage() { sed -n '2,19p' "$0" | sed 's/^# \{0,1\}//' >&2; exit 2; }
[ $# -ge 1 ] || usage
say() { echo "apt-repo: $*" >&2; }
need() { # COMMAND PACKAGE
  command -v "$1" >/dev/null || { apt-get update -qq && apt-get install -y -qq "$2" >/dev/null; }
}
channels=(stable beta)

gpg_home() { # DIR: the key the repository signs with
  if [ -n "${NORI_APT_KEY:-}" ]; then echo "${GNUPGHOME:-$HOME/.gnupg}"; else echo "$1/gnupg"; fi
}

init() { # DIR
  local dir=$1 home key
  need reprepro reprepro
  need gpg gpg
  [ ! -e "$dir/conf/distributions" ] || { say "$dir is already a repository"; exit 1; }
  mkdir -p "$dir/conf" "$dir/public"
  home=$(gpg_home "$dir")
  if [ -n "${NORI_APT_KEY:-}" ]; then
    # A whole fingerprint: a name or a short id could export more keys than the one meant into
    # what every robot trusts.
    [[ $NORI_APT_KEY =~ ^[0-9A-Fa-f]{40}$ ]] || { say "NORI_APT_KEY is a key's 40-digit fingerprint"; exit 2; }
    key=$NORI_APT_KEY
  else
    # A key of this repository's own, without a passphrase: for a test fleet. A real fleet's
    # key is made and kept offline by whoever answers for what robots run (NORI_APT_KEY).
    mkdir -p -m 700 "$home"
    GNUPGHOME=$home gpg --batch --quiet --passphrase '' \
      --quick-generate-key "Nori fleet archive (test) <robots@nori.invalid>" ed25519 sign 2y \
      2>"$home/keygen.log" || { cat "$home/keygen.log" >&2; exit 1; }
    key=$(GNUPGHOME=$home gpg --batch --trust-model always --with-colons --list-secret-keys | awk -F: '$1 == "fpr" {print $10; exit}')
  fi
  GNUPGHOME=$home gpg --batch --quiet --trust-model always --export "$key" >"$dir/public/nori-archive-keyring.gpg"
  for c in "${channels[@]}"; do
    printf 'Origin: Nori Robotics\nLabel: nori\nSuite: %s\nCodename: %s\nArchitectures: amd64 arm64\nComponents: main\nDescription: Nori A3 robot packages, %s channel\nSignWith: %s\n\n' \
      "$c" "$c" "$c" "$key"
  done >"$dir/conf/distributions"
  # What robots fetch is apart from the database and the configuration.
  echo "outdir +b/public" >"$dir/conf/options"
  GNUPGHOME=$home reprepro --silent -b "$dir" export
  say "$dir: channels ${channels[*]}, signed by $key; serve $dir/public"
}

# Whether CHANNEL holds PACKAGE at VERSION for ARCH.
holds() { # DIR CHANNEL PACKAGE VERSION ARCH
  reprepro -b "$1" -A "$5" list "$2" "$3" | grep -q " $4\$"
}

channel_of() { # CHANNEL
  case " ${channels[*]} " in *" $1 "*) ;; *) say "no channel $1 (${channels[*]})"; exit 2 ;; esac
}

cmd=$1; shift
case $cmd in
  init) [ $# -eq 1 ] || usage; init "$1" ;;
  publish)
    [ $# -ge 2 ] || usage
    dir=$1; shift
    for deb in "$@"; do
      GNUPGHOME=$(gpg_home "$dir") reprepro --silent -b "$dir" includedeb beta "$deb"
      read -r pkg version arch < <(dpkg-deb -W --showformat='${Package} ${Version} ${Architecture}\n' "$deb")
      holds "$dir" beta "$pkg" "$version" "$arch" || { say "beta does not hold $pkg $version ($arch) after publishing it"; exit 1; }
      say "beta: $pkg $version ($arch)"
    done
    ;;
  promote)
    [ $# -eq 2 ] || usage
    dir=$1 version=$2
    # Exactly what beta holds of VERSION, every package and architecture of it, and then
    # stable must hold each (reprepro skips what it will not replace, with only a word).
    promoted=$(reprepro -b "$dir" --list-format '${package} ${architecture}\n' listfilter beta "Version (== $version)")
    [ -n "$promoted" ] || { say "beta holds nothing of version $version"; exit 1; }
    GNUPGHOME=$(gpg_home "$dir") reprepro --silent -b "$dir" copyfilter stable beta "Version (== $version)"
    while read -r pkg arch; do
      holds "$dir" stable "$pkg" "$version" "$arch" || { say "stable does not hold $pkg $version ($arch) after the promotion"; exit 1; }
      say "stable: $pkg $version ($arch)"
    done <<<"$promoted"
    ;;
  list)
    [ $# -eq 1 ] || usage
    for c in "${channels[@]}"; do reprepro -b "$1" list "$c"; done
    ;;
  sources)
    [ $# -eq 2 ] || usage
    channel_of "$2"
    printf 'Types: deb\nURIs: %s\nSuites: %s\nComponents: main\nSigned-By: /usr/share/keyrings/nori-archive-keyring.gpg\n' "$1" "$2"
    ;;
  serve)
    [ $# -eq 2 ] || usage
    need nginx nginx-light
    dir=$(realpath "$1") listen=$2
    run=$(mktemp -d)
    # Only the public tree, read-only; nginx's workers must be able to read it.
    chmod -R a+rX "$dir/public"
    cat >"$run/nginx.conf" <<EOF
daemon off;
pid $run/nginx.pid;
error_log stderr warn;
events {}
http {
  access_log off;
  types { application/octet-stream deb; text/plain gpg; }
  server {
    listen $listen;
    root $dir/public;
    autoindex off;
    location / { limit_except GET HEAD { deny all; } }
  }
}
EOF
    say "serving $dir/public on http://$listen/"
    exec nginx -e stderr -p "$run" -c "$run/nginx.conf"
    ;;
  *) usage ;;
esac
