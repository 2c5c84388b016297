#!/bin/sh
# The yard's TLS certificates, made on site with openssl. Nothing this writes belongs in git.
#
#   deploy/make-certs.sh DIR ca                      the yard CA: DIR/ca.key (0600), DIR/ca.crt (0644)
#   deploy/make-certs.sh DIR router NAME [NAME...]   the router's key and certificate, signed by the CA,
#                                                    valid for every DNS name and IP address given
#   deploy/make-certs.sh DIR tablet NAME [NAME...]   the same for the tablet app's HTTPS pages (tablet.key,
#                                                    tablet.crt; tablet_tls_cert/tablet_tls_key in its config)
#   deploy/make-certs.sh DIR show                    what DIR holds and when each certificate expires
#
#   e.g. deploy/make-certs.sh /root/yard-ca ca
#        deploy/make-certs.sh /root/yard-ca router yard-router yard-router.local 10.20.0.2
#
# Validity: the CA 10 years (CA_DAYS), the router's certificate 1 year (DAYS); both may be set in the
# environment. Keys are EC P-256, certificates SHA-256. `cellctl doctor` warns 30 days before expiry.
#
# Who holds what:
# - ca.key signs certificates: keep it off the yard network (an offline PC or a USB key in a safe).
# - ca.crt is public: every cell, CLI and tablet app is given it (service.tls_ca_file, --ca, tls_ca).
# - router.key and router.crt go to the router host only (/etc/scrapcell/tls/, key 0600).
#
# Rotation (docs: deploy/README.md, "Certificates"):
# - the router's certificate: run `router` again (the old pair is kept as *.old), copy both files to
#   the router host and restart it. Cells and tablets change nothing: they trust the CA.
# - the CA: make a new one in a NEW directory, give every client the two CA certificates in one file
#   (cat old/ca.crt new/ca.crt > ca.crt), issue the router's certificate from the new CA, then drop
#   the old CA certificate from the clients' file.
set -eu

usage() { sed -n '2,11p' "$0" >&2; exit 2; }
[ $# -ge 2 ] || usage
dir=$1
what=$2
shift 2
CA_DAYS=${CA_DAYS:-3650}
DAYS=${DAYS:-365}

umask 077
mkdir -p "$dir"
if git -C "$dir" rev-parse --is-inside-work-tree >/dev/null 2>&1; then
  echo "make-certs.sh: $dir is inside a git work tree; keys must never be committed: choose another directory" >&2
  rmdir "$dir" 2>/dev/null || true
  exit 1
fi

expiry() { openssl x509 -in "$1" -noout -enddate | sed 's/notAfter=/expires /'; }

case "$what" in
ca)
  [ $# -eq 0 ] || usage
  if [ -e "$dir/ca.key" ]; then
    echo "make-certs.sh: $dir/ca.key exists; a new CA goes in a new directory (see Rotation in $0)" >&2
    exit 1
  fi
  openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$dir/ca.key" 2>/dev/null
  openssl req -x509 -new -key "$dir/ca.key" -sha256 -days "$CA_DAYS" -subj "/O=scrapcell yard/CN=scrapcell yard CA" \
    -addext "basicConstraints=critical,CA:TRUE,pathlen:0" -addext "keyUsage=critical,keyCertSign,cRLSign" \
    -addext "subjectKeyIdentifier=hash" -out "$dir/ca.crt"
  chmod 600 "$dir/ca.key"
  chmod 644 "$dir/ca.crt"
  echo "wrote $dir/ca.key (keep it offline) and $dir/ca.crt (give it to every cell and tablet), $(expiry "$dir/ca.crt")"
  ;;
router|tablet)
  [ $# -ge 1 ] || usage
  [ -f "$dir/ca.key" ] && [ -f "$dir/ca.crt" ] || { echo "make-certs.sh: no CA in $dir: run '$0 $dir ca' first" >&2; exit 1; }
  san=""
  for name in "$@"; do
    case "$name" in
    *[!0-9.]*) case "$name" in *:*) entry="IP:$name" ;; *) entry="DNS:$name" ;; esac ;;
    *) entry="IP:$name" ;;
    esac
    san="${san:+$san,}$entry"
  done
  for f in "$what.key" "$what.crt"; do
    [ -e "$dir/$f" ] && mv -f "$dir/$f" "$dir/$f.old"
  done
  openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$dir/$what.key" 2>/dev/null
  ext=$(mktemp)
  trap 'rm -f "$ext" "$dir/$what.csr"' EXIT
  printf '%s\n' "basicConstraints=critical,CA:FALSE" "keyUsage=critical,digitalSignature" \
    "extendedKeyUsage=serverAuth" "subjectAltName=$san" "authorityKeyIdentifier=keyid" > "$ext"
  openssl req -new -key "$dir/$what.key" -subj "/O=scrapcell yard/CN=$1" -out "$dir/$what.csr"
  openssl x509 -req -in "$dir/$what.csr" -CA "$dir/ca.crt" -CAkey "$dir/ca.key" -CAcreateserial \
    -days "$DAYS" -sha256 -extfile "$ext" -out "$dir/$what.crt" 2>/dev/null
  chmod 600 "$dir/$what.key"
  chmod 644 "$dir/$what.crt"
  echo "wrote $dir/$what.key and $dir/$what.crt for $san, $(expiry "$dir/$what.crt")"
  ;;
show)
  for f in "$dir"/*.crt; do
    [ -f "$f" ] || continue
    echo "$f: $(openssl x509 -in "$f" -noout -subject | sed 's/^subject=//'), $(expiry "$f")"
    openssl x509 -in "$f" -noout -ext subjectAltName 2>/dev/null | sed -n '2p' | sed 's/^ */  names: /'
  done
  ;;
*) usage ;;
esac
