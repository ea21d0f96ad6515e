#!/bin/sh
# Make a base image for docker/Dockerfile from Debian's packages, with no container registry:
# mmdebstrap builds a minimal Debian (python3, python3-venv, ca-certificates) from a Debian
# mirror and `docker import` turns the tree into an image.
#
#   docker/make-base.sh                       # -> socmon-base:bookworm
#   docker/make-base.sh --host-ca             # also trust the CAs this host trusts
#   docker build -f docker/Dockerfile --build-arg BASE=socmon-base:bookworm -t socmon .
#
# Options:
#   --tag TAG         image name (default socmon-base:<suite>)
#   --suite SUITE     Debian suite (default bookworm: Python 3.11)
#   --mirror URL      Debian mirror (default: mmdebstrap's, deb.debian.org)
#   --host-ca[=FILE]  add the certificates of FILE (a PEM bundle; default $PIP_CERT, else
#                     $SSL_CERT_FILE, else /etc/ssl/certs/ca-certificates.crt) that Debian's
#                     ca-certificates does not already hold to the image's trust store: where
#                     HTTPS goes through a TLS-intercepting proxy, pip in the build needs the
#                     proxy's CA, which the host has and a fresh Debian has not
# Needs mmdebstrap (Debian package `mmdebstrap`; as root it builds in a chroot, otherwise in
# a user namespace) and a Docker engine. The image sets PIP_CERT to the system bundle, so
# pip trusts what the image's trust store holds.
set -eu

suite=bookworm
tag=
mirror=
ca=
while [ $# -gt 0 ]; do
    case "$1" in
        --tag) tag=$2; shift 2 ;;
        --suite) suite=$2; shift 2 ;;
        --mirror) mirror=$2; shift 2 ;;
        --host-ca) ca=${PIP_CERT:-${SSL_CERT_FILE:-/etc/ssl/certs/ca-certificates.crt}}; shift ;;
        --host-ca=*) ca=${1#--host-ca=}; shift ;;
        -h|--help) sed -n '2,/^set -eu/p' "$0" | sed '$d; s/^# \{0,1\}//'; exit 0 ;;
        *) echo "make-base.sh: unknown argument $1 (see --help)" >&2; exit 2 ;;
    esac
done
tag=${tag:-socmon-base:$suite}
for tool in mmdebstrap docker; do
    command -v "$tool" > /dev/null || { echo "make-base.sh: $tool not found" >&2; exit 1; }
done
if [ -n "$ca" ] && [ ! -r "$ca" ]; then
    echo "make-base.sh: no CA bundle at $ca" >&2; exit 1
fi

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
# the hook runs after the packages are installed, with the image's root as $1: each
# certificate of the bundle that the image's bundle lacks becomes a file of
# /usr/local/share/ca-certificates, then update-ca-certificates rebuilds the bundle
cat > "$work/ca-hook.sh" << 'EOF'
#!/bin/sh
set -eu
root=$1 bundle=$2 out=$1/usr/local/share/ca-certificates
mkdir -p "$out"
awk -v dir="$out" -v have="$root/etc/ssl/certs/ca-certificates.crt" '
    BEGIN { while ((getline line < have) > 0) {
                if (line ~ /BEGIN CERTIFICATE/) { body = "" }
                else if (line ~ /END CERTIFICATE/) { known[body] = 1 }
                else { body = body line } } }
    /BEGIN CERTIFICATE/ { pem = $0 "\n"; body = ""; inside = 1; next }
    inside { pem = pem $0 "\n" }
    inside && /END CERTIFICATE/ { inside = 0
        if (!(body in known)) { n++; f = sprintf("%s/host-ca-%03d.crt", dir, n)
                                printf "%s", pem > f; close(f) }
        next }
    inside { body = body $0 }
    END { print n + 0 " certificate(s) added from the host bundle" }' "$bundle"
chroot "$root" update-ca-certificates 2>&1 > /dev/null | grep -v "does not contain exactly one" >&2 || true
EOF
chmod +x "$work/ca-hook.sh"

set -- --variant=minbase --include=python3,python3-venv,ca-certificates \
    --aptopt='Acquire::Languages "none"' --dpkgopt='path-exclude=/usr/share/doc/*' \
    --dpkgopt='path-include=/usr/share/doc/*/copyright' \
    --dpkgopt='path-exclude=/usr/share/man/*' --dpkgopt='path-exclude=/usr/share/locale/*'
if [ -n "$ca" ]; then
    set -- "$@" --customize-hook="$work/ca-hook.sh \"\$1\" \"$ca\""
fi
set -- "$@" --customize-hook='rm -rf "$1"/var/lib/apt/lists/* "$1"/var/cache/apt/*.bin'
set -- "$@" "$suite" "$work/rootfs.tar"
[ -n "$mirror" ] && set -- "$@" "$mirror"

start=$(date +%s)
mmdebstrap --quiet "$@"
docker import \
    --change 'ENV LANG=C.UTF-8' \
    --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    --change 'ENV PIP_CERT=/etc/ssl/certs/ca-certificates.crt' \
    --change 'CMD ["python3"]' \
    --message "mmdebstrap --variant=minbase $suite: python3, python3-venv, ca-certificates" \
    "$work/rootfs.tar" "$tag" > /dev/null
echo "$tag: $(docker run --rm "$tag" python3 --version), made in $(( $(date +%s) - start )) s," \
     "$(docker image inspect --format '{{.Size}}' "$tag" | awk '{printf "%.0f MB", $1/1e6}')"
