# (Sourced by deploy/deb/check.sh and deploy/deb/boot-check.sh.)
# Builds version N ($n) of the packages into WORK/n and N+1 ($next) into WORK/next, from the
# binaries in BIN_DIR. N+1 changes the default of the file the robot edits (supervisor.toml), so
# dpkg has a conffile to decide on; its binaries are N's (what is checked is the packaging, not
# a change of code).
build_two_versions() { # ARCH BIN_DIR WORK
  n=0.1.0+$(git rev-list --count HEAD)
  next=$n.1
  export NORI_DEB_COMPRESSION=${NORI_DEB_COMPRESSION:-gzip}
  deploy/deb/build.sh "$1" "$2" "$3/n" "$n"
  cp -r deploy/config "$3/config-next"
  printf '\n# a default changed in %s\n' "$next" >>"$3/config-next/supervisor.toml"
  NORI_DEB_CONFIG="$3/config-next" deploy/deb/build.sh "$1" "$2" "$3/next" "$next"
}
