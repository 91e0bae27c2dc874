#!/usr/bin/env bash
# Builds a Debian package of visnav with plain dpkg-deb (no cargo-deb, no debhelper):
#
#   cargo build --release --no-default-features     # the flight build (or any visnav binary)
#   scripts/build_deb.sh target/release/visnav dist # -> dist/visnav_VERSION_ARCH.deb
#   sudo apt install ./dist/visnav_VERSION_ARCH.deb
#
# The files are what scripts/install.sh installs, staged by it (--root): the same unit and the
# same configuration (config/companion.toml and the files it names), with the binary in /usr/bin
# and the unit in /usr/lib/systemd/system as packages have them. /etc/visnav's files are
# conffiles: an edited configuration survives upgrades. The maintainer scripts
# (packaging/debian/) create the system user 'visnav' and /var/log/visnav, and enable or start
# nothing.
set -euo pipefail
umask 022

prog=build_deb.sh
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"

usage() {
    cat <<EOF
Usage: scripts/build_deb.sh [options] BINARY OUTDIR

Builds OUTDIR/visnav_VERSION_ARCH.deb from the visnav binary BINARY and prints its path.
VERSION is the package version in Cargo.toml.

  --config FILE        the configuration installed as /etc/visnav/visnav.toml
                       (default config/companion.toml, as scripts/install.sh)
  --arch ARCH          the Debian architecture (default: dpkg --print-architecture); a
                       cross-compiled binary needs its own, e.g. --arch arm64 for
                       aarch64-unknown-linux-gnu
  --maintainer TEXT    the Maintainer field, "NAME <EMAIL>" (default: \$DEBFULLNAME <\$DEBEMAIL>
                       when both are set, else "visnav <visnav@localhost>")
  --compression TYPE   xz (default), gzip, zstd or none (dpkg-deb -Z)
  -h, --help           this text

Depends: libc6 at the newest GLIBC symbol version the binary uses, libgcc-s1 when it links
libgcc_s (Debian 11, Ubuntu 20.04 or newer), adduser or passwd for the maintainer scripts.
EOF
}

die() {
    echo "$prog: error: $*" >&2
    exit 1
}

usage_error() {
    echo "$prog: $*" >&2
    echo "$prog: see '$0 --help'" >&2
    exit 2
}

need_value() {
    [ "$2" -ge 2 ] || usage_error "option $1 needs a value"
}

config=""
arch=""
maintainer=""
compression=xz
args=()
while [ $# -gt 0 ]; do
    case "$1" in
        --config) need_value "$1" $#; config="$2"; shift 2 ;;
        --config=*) config="${1#*=}"; shift ;;
        --arch) need_value "$1" $#; arch="$2"; shift 2 ;;
        --arch=*) arch="${1#*=}"; shift ;;
        --maintainer) need_value "$1" $#; maintainer="$2"; shift 2 ;;
        --maintainer=*) maintainer="${1#*=}"; shift ;;
        --compression) need_value "$1" $#; compression="$2"; shift 2 ;;
        --compression=*) compression="${1#*=}"; shift ;;
        -h | --help) usage; exit 0 ;;
        --) shift; args+=("$@"); break ;;
        -*) usage_error "unknown option '$1'" ;;
        *) args+=("$1"); shift ;;
    esac
done
[ ${#args[@]} -eq 2 ] || usage_error "expected BINARY and OUTDIR, got ${#args[@]} arguments"
binary="${args[0]}"
outdir="${args[1]}"

command -v dpkg-deb >/dev/null 2>&1 || die "dpkg-deb not found (the dpkg package): this builds on Debian or Ubuntu"
[ -f "$binary" ] || die "$binary: no such file"
[ -x "$binary" ] || die "$binary: not executable"
case "$compression" in
    xz | gzip | zstd | none) ;;
    *) usage_error "--compression $compression: one of xz, gzip, zstd, none" ;;
esac

# --- version, architecture, maintainer ---------------------------------------------------------
# The [package] section's version of the workspace's root Cargo.toml (the binary's).
version="$(awk '
    /^\[/ { in_package = ($0 == "[package]") }
    in_package && /^version[[:space:]]*=/ { sub(/^version[[:space:]]*=[[:space:]]*"/, ""); sub(/".*/, ""); print; exit }
' "$repo/Cargo.toml")"
[[ "$version" =~ ^[0-9][A-Za-z0-9.+~-]*$ ]] || die "$repo/Cargo.toml: no usable [package] version (found '$version')"

if [ -z "$arch" ]; then
    command -v dpkg >/dev/null 2>&1 || die "dpkg not found: give --arch"
    arch="$(dpkg --print-architecture)"
fi
[[ "$arch" =~ ^[a-z0-9-]+$ ]] || usage_error "--arch '$arch': not a Debian architecture name"

# The binary's machine (ELF e_machine, little-endian machines only) against the architecture:
# a package that says amd64 around an aarch64 binary installs and then cannot run.
[ "$(head -c 4 "$binary" | od -An -c | tr -d ' ')" = '177ELF' ] || die "$binary: not an ELF executable"
machine="$(od -An -tx1 -j18 -N2 "$binary" | tr -d ' \n')"
case "$machine" in
    3e00) elf_arch=amd64 ;;
    b700) elf_arch=arm64 ;;
    2800) elf_arch="armhf armel" ;;
    0300) elf_arch=i386 ;;
    f300) elf_arch="riscv64" ;;
    *) elf_arch="" ;;
esac
if [ -n "$elf_arch" ] && [[ " $elf_arch " != *" $arch "* ]]; then
    die "$binary is built for $elf_arch, not $arch: give --arch ${elf_arch%% *} (or the binary for $arch)"
fi

if [ -z "$maintainer" ]; then
    if [ -n "${DEBFULLNAME:-}" ] && [ -n "${DEBEMAIL:-}" ]; then
        maintainer="$DEBFULLNAME <$DEBEMAIL>"
    else
        maintainer="visnav <visnav@localhost>"
    fi
fi
case "$maintainer" in *"<"*"@"*">") ;; *) usage_error "--maintainer '$maintainer': expected \"NAME <EMAIL>\"" ;; esac

# Shared libraries: libc6 from the newest GLIBC_x.y symbol version the binary names, libgcc-s1
# when it links libgcc_s (Rust's unwinder). Anything else it links must be named by hand.
depends=()
glibc="$(grep -aoE 'GLIBC_2\.[0-9]+(\.[0-9]+)?' "$binary" | sed 's/^GLIBC_//' | sort -uV | tail -n 1 || true)"
[ -z "$glibc" ] || depends+=("libc6 (>= $glibc)")
if grep -aq 'libgcc_s\.so\.1' "$binary"; then
    depends+=("libgcc-s1")
fi
if command -v readelf >/dev/null 2>&1; then
    while IFS= read -r lib; do
        case "$lib" in
            libc.so.* | libm.so.* | libpthread.so.* | libdl.so.* | librt.so.* | ld-linux*.so.* | libgcc_s.so.*) ;;
            *) die "$binary links $lib, which this script does not know the package of: build without the feature that needs it, or add the package to Depends in $0" ;;
        esac
    done < <(readelf -d "$binary" 2>/dev/null | sed -n 's/.*(NEEDED).*\[\(.*\)\]/\1/p')
fi
depends+=("adduser | passwd")
depends_field="$(IFS=,; echo "${depends[*]}" | sed 's/,/, /g')"

# --- the staging tree, by scripts/install.sh ---------------------------------------------------
stage="$(mktemp -d)"
trap 'rm -rf "$stage"' EXIT
root="$stage/root"
mkdir -m 0755 "$root"
install_args=(--root "$root" --prefix /usr --binary "$binary" --no-enable)
[ -z "$config" ] || install_args+=(--config "$config")
if ! "$repo/scripts/install.sh" "${install_args[@]}" >"$stage/install.log" 2>"$stage/install.err"; then
    cat "$stage/install.log" "$stage/install.err" >&2
    die "scripts/install.sh --root failed (above)"
fi
# Its warnings (files the configuration names that are not there, ...) hold for the package too.
sed 's/^install\.sh: /build_deb.sh: (install.sh) /' "$stage/install.err" >&2

# The unit where packages put theirs (/etc/systemd/system is the administrator's), its header
# saying who installed it.
unit="$root/usr/lib/systemd/system/visnav.service"
install -d -m 0755 "$(dirname "$unit")"
mv "$root/etc/systemd/system/visnav.service" "$unit"
rmdir "$root/etc/systemd/system" "$root/etc/systemd" 2>/dev/null || true
sed -i \
    -e 's/(installed by scripts\/install\.sh)\./(installed by the visnav Debian package)./' \
    -e 's/^# scripts\/install\.sh rewrites this file\.$/# a package upgrade rewrites this file./' \
    "$unit"
! grep -q 'install\.sh' "$unit" || die "$unit: scripts/install.sh's unit header changed; update the rewrite in $0"

# The configuration's header: no build machine's paths or dates.
conf="$root/etc/visnav/visnav.toml"
[ -f "$conf" ] || die "scripts/install.sh wrote no $conf"
tmp="$stage/visnav.toml"
first=1
while IFS= read -r line || [ -n "$line" ]; do
    if [ "$first" = 1 ]; then
        first=0
        case "$line" in
            "# Installed by scripts/install.sh from "*)
                src="${line#"# Installed by scripts/install.sh from "}"
                src="${src% on *}"
                src="${src#"$repo/"}"
                line="# Installed by the visnav $version Debian package from $src."
                ;;
        esac
    elif [[ "$line" == "#"* ]]; then
        line="${line//"$repo/"/the repository\'s }"
    fi
    printf '%s\n' "$line"
done <"$conf" >"$tmp"
install -m 0644 "$tmp" "$conf"

# The flight records' folder belongs to the visnav user: postinst makes it.
rm -rf "${root:?}/var/log/visnav"
rmdir "$root/var/log" "$root/var" 2>/dev/null || true

# --- DEBIAN/ -----------------------------------------------------------------------------------
debian="$root/DEBIAN"
install -d -m 0755 "$debian"
for script in postinst prerm postrm; do
    install -m 0755 "$repo/packaging/debian/$script" "$debian/$script"
done
(cd "$root" && find etc -type f | LC_ALL=C sort | sed 's|^|/|') >"$debian/conffiles"
(cd "$root" && find . -path ./DEBIAN -prune -o -type f -print | LC_ALL=C sort | sed 's|^\./||' \
    | xargs -r md5sum) >"$debian/md5sums"
installed_kb="$(du -sk --exclude=DEBIAN "$root" | cut -f1)"
cat >"$debian/control" <<EOF
Package: visnav
Version: $version
Architecture: $arch
Maintainer: $maintainer
Installed-Size: $installed_kb
Depends: $depends_field
Recommends: systemd
Section: misc
Priority: optional
Description: vision-aided navigation for drones without GPS
 visnav runs on the companion computer: it reads IMU and attitude from the
 autopilot over MAVLink, matches camera frames against a georeferenced
 orthophoto and elevation model, fuses the fixes with the IMU and injects the
 position into ArduPilot or PX4 (GPS_INPUT or external vision).
 .
 The package installs the binary, the systemd unit visnav.service (not enabled)
 and an example configuration /etc/visnav/visnav.toml to edit first.
EOF

# --- the package -------------------------------------------------------------------------------
mkdir -p "$outdir" || die "cannot create $outdir"
deb="$outdir/visnav_${version}_${arch}.deb"
dpkg-deb --root-owner-group -Z"$compression" --build "$root" "$deb" >/dev/null \
    || die "dpkg-deb --build failed"
echo "$deb"
