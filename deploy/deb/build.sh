#!/usr/bin/env bash
# The robot's Debian packages, from binaries already built:
#
#   deploy/deb/build.sh ARCH BIN_DIR OUT_DIR [VERSION]
#
#   ARCH     amd64 or arm64 (the binaries' architecture: it is checked)
#   BIN_DIR  target/release, target/tested (CI: the binaries its tests ran), or
#            target/aarch64-unknown-linux-gnu/release (deploy/arm64/cross.sh)
#   VERSION  the packages' version; by default 0.1.0+<commits on HEAD>, so a later commit's
#            packages upgrade an earlier one's
#   NORI_DEB_COMPRESSION  xz (the default) or gzip or none (quicker, for checks)
#   NORI_DEB_CONFIG  the folder of /etc/nori's defaults (deploy/config; check.sh changes one)
#
# makes OUT_DIR/nori-robot_VERSION_ARCH.deb (the on-robot binaries, nori-upgrade, the systemd
# units, the udev rules, the nori user, /usr/lib/nori/version, /etc/nori's configuration as
# conffiles, /var/lib/nori) and
# OUT_DIR/nori-sim_VERSION_ARCH.deb (the simulator and `nori up`). What the maintainer scripts
# promise on an upgrade (the stack stopped whole before any file changes, started again after,
# the trip record and edited configuration kept): deploy/README.md, "Packages and upgrades".
set -euo pipefail
cd "$(dirname "$0")/../.."
repo=$(pwd)
[ $# -ge 3 ] || { sed -n '2,18p' "$0" | sed 's/^# \{0,1\}//' >&2; exit 2; }
arch=$1 bin_dir=$(realpath "$2") out=$3
version=${4:-0.1.0+$(git -C "$repo" rev-list --count HEAD)}
case $arch in
  amd64) machine="X86-64" strip=strip ;;
  arm64) machine="AArch64" strip=aarch64-linux-gnu-strip ;;
  *) echo "deb: ARCH is amd64 or arm64, not $arch" >&2; exit 2 ;;
esac
command -v $strip >/dev/null || { echo "deb: $strip missing (apt install binutils-aarch64-linux-gnu)" >&2; exit 1; }

# shellcheck source=deploy/binaries.sh
. deploy/binaries.sh
mkdir -p "$out"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

# The newest glibc symbol version any of the binaries asks for: the packages' libc6 dependency.
glibc_floor() {
  for b in "$@"; do
    readelf --dyn-syms --wide "$bin_dir/$b" | grep -o 'GLIBC_[0-9.]*' | sed 's/GLIBC_//'
  done | sort -uV | tail -1
}

install_bins() { # PKGROOT BIN...
  local root=$1; shift
  install -d "$root/usr/bin"
  for b in "$@"; do
    [ -x "$bin_dir/$b" ] || { echo "deb: $bin_dir/$b is missing: build it first" >&2; exit 1; }
    local m
    m=$(readelf -h "$bin_dir/$b" | sed -n 's/ *Machine: *//p')
    case $m in *"$machine"*) ;; *) echo "deb: $b is for $m, not $arch" >&2; exit 1 ;; esac
    # Stripped of debug sections: the Pi's SD card, and what lintian asks.
    $strip --strip-unneeded -o "$root/usr/bin/$b" "$bin_dir/$b"
    chmod 755 "$root/usr/bin/$b"
  done
}

docs() { # PKGROOT PACKAGE
  local d=$1/usr/share/doc/$2
  install -d "$d"
  cat >"$d/copyright" <<EOF
Format: https://www.debian.org/doc/packaging-manuals/copyright-format/1.0/
Upstream-Name: nori
Source: https://github.com/nori-robotics/nori

Files: *
Copyright: 2026 Nori Robotics
License: Apache-2.0
 On Debian systems the full text of the Apache License 2.0 is in
 /usr/share/common-licenses/Apache-2.0.
EOF
  printf '%s (%s) unstable; urgency=medium\n\n  * Built from %s.\n\n -- Nori Robotics <robots@nori.invalid>  %s\n' \
    "$2" "$version" "$(git -C "$repo" rev-parse --short HEAD)" \
    "$(date -R -d "@$(git -C "$repo" log -1 --format=%ct)")" | gzip -9n >"$d/changelog.gz"
  # What lintian says that is meant, each with its reason.
  install -d "$1/usr/share/lintian/overrides"
  install -m 644 "deploy/deb/$2.lintian-overrides" "$1/usr/share/lintian/overrides/$2"
}

control() { # PKGROOT PACKAGE DEPENDS DESCRIPTION...
  local root=$1 pkg=$2 depends=$3; shift 3
  install -d "$root/DEBIAN"
  {
    echo "Package: $pkg"
    echo "Version: $version"
    echo "Architecture: $arch"
    echo "Maintainer: Nori Robotics <robots@nori.invalid>"
    echo "Installed-Size: $(du -sk --exclude=DEBIAN "$root" | cut -f1)"
    echo "Depends: $depends"
    echo "Section: misc"
    echo "Priority: optional"
    echo "Homepage: https://github.com/nori-robotics/nori"
    for line in "$@"; do echo "$line"; done
  } >"$root/DEBIAN/control"
}

robot_package() {
  local root=$work/nori-robot
  install_bins "$root" "${robot_bins[@]}"
  install -d "$root/etc/nori" "$root/usr/lib/systemd/system" "$root/usr/lib/udev/rules.d" \
    "$root/usr/lib/sysusers.d" "$root/usr/lib/tmpfiles.d"
  local config=${NORI_DEB_CONFIG:-deploy/config} f
  for f in "$config"/*.toml; do
    # The embedded calibration is the simulated A3's: a robot's own is state, written by
    # `nori calibrate` to /var/lib/nori, never a conffile (an upgrade must not put one back).
    [ "$(basename "$f")" = calibration.toml ] || install -m 644 "$f" "$root/etc/nori/"
  done
  sed -i 's|^# calibration-file = "calibration.toml"$|calibration-file = "/var/lib/nori/calibration.toml"|' \
    "$root/etc/nori/bus-driver.toml"
  grep -qx 'calibration-file = "/var/lib/nori/calibration.toml"' "$root/etc/nori/bus-driver.toml" \
    || { echo "build.sh: the packaged bus-driver.toml does not name /var/lib/nori/calibration.toml" >&2; exit 1; }
  install -m 644 deploy/systemd/*.service deploy/systemd/nori.target "$root/usr/lib/systemd/system/"
  install -m 644 deploy/udev/*.rules "$root/usr/lib/udev/rules.d/"
  install -m 644 deploy/systemd/nori.sysusers.conf "$root/usr/lib/sysusers.d/nori.conf"
  # What the fleet agent reports the robot runs (fleet_agent::installed), and the upgrade from
  # the fleet's repository (deploy/apt).
  install -d "$root/usr/lib/nori" "$root/usr/sbin"
  echo "$version" >"$root/usr/lib/nori/version"
  install -m 755 deploy/apt/nori-upgrade "$root/usr/sbin/nori-upgrade"
  # /var/lib/nori (the trip record, the lift's hold, the journal) is made by tmpfiles, owned by
  # nori: the package never ships a file there, so no upgrade or removal touches what is in it.
  echo 'd /var/lib/nori 0750 nori nori -' >"$root/usr/lib/tmpfiles.d/nori.conf"
  docs "$root" nori-robot
  control "$root" nori-robot "libc6 (>= $(glibc_floor "${robot_bins[@]}")), libgcc-s1, systemd (>= 247), udev" \
    "Description: Nori A3 on-robot control stack" \
    " The bus driver, the supervisor, the fleet agent, the base and lift" \
    " controllers, the camera and lidar processes and the recorder of the" \
    " Nori A3 bimanual mobile manipulator, with their systemd units" \
    " (nori.target), udev rules and default configuration."
  (cd "$root" && find etc -type f | sed 's|^|/|' | sort) >"$root/DEBIAN/conffiles"
  for s in preinst postinst prerm postrm; do
    # One rule for stopping the stack and recording what ran, in every script.
    grep -qx '#NORI_COMMON#' "deploy/deb/nori-robot.$s" || { echo "deb: nori-robot.$s lacks #NORI_COMMON#" >&2; exit 1; }
    sed -e '/^#NORI_COMMON#$/{r deploy/deb/maintainer-common.sh' -e 'd}' "deploy/deb/nori-robot.$s" >"$root/DEBIAN/$s"
    chmod 755 "$root/DEBIAN/$s"
  done
  dpkg-deb --root-owner-group "-Z${NORI_DEB_COMPRESSION:-xz}" --build "$root" "$out/nori-robot_${version}_$arch.deb" >/dev/null
}

sim_package() {
  local root=$work/nori-sim
  install_bins "$root" "${sim_bins[@]}"
  docs "$root" nori-sim
  control "$root" nori-sim "libc6 (>= $(glibc_floor "${sim_bins[@]}")), libgcc-s1, nori-robot (= $version)" \
    "Description: Nori A3 simulated robot, for development" \
    " The simulator of the Nori A3's servo buses, lift, base, lidar and" \
    " cameras on pseudo-terminals, and \`nori up\`, which runs the packaged" \
    " stack against it."
  dpkg-deb --root-owner-group "-Z${NORI_DEB_COMPRESSION:-xz}" --build "$root" "$out/nori-sim_${version}_$arch.deb" >/dev/null
}

robot_package
sim_package
ls -l "$out"/nori-{robot,sim}_"${version}_$arch".deb | awk '{print "deb: " $NF ": " $5 " bytes"}' >&2
