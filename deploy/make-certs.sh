#!/usr/bin/env bash
# make-certs.sh: a private certificate authority and a TLS server certificate for matoptd.
#
# Usage: make-certs.sh [-o OUTDIR] [-d DAYS] [-f] NAME [NAME...]
#
#   NAME      a DNS name or an IP address (IPv4 or IPv6) clients use to reach the daemon.
#             Every NAME goes into the certificate's subjectAltName; the first is also its
#             common name. Clients check the name they dial against this list, so give every
#             name and address they will use (add localhost and 127.0.0.1 for checks on the
#             server itself).
#   -o DIR    where to write the files (default: current directory)
#   -d DAYS   validity of the server certificate in days (default: 825); the CA gets 3650
#   -f        replace an existing server certificate and key in OUTDIR
#
# If OUTDIR already holds ca.pem and ca.key, that CA is reused, so a renewed or re-issued
# server certificate needs no change on the clients.
#
# Example: make-certs.sh -o ./certs gpu1.example.org 192.0.2.10 localhost 127.0.0.1
set -euo pipefail

usage() { sed -n '2,18p' "$0" | sed 's/^# \{0,1\}//'; }
die() { echo "make-certs.sh: $*" >&2; exit 1; }

outdir=.
days=825
force=0
while getopts ':o:d:fh' opt; do
  case "$opt" in
    o) outdir=$OPTARG ;;
    d) days=$OPTARG ;;
    f) force=1 ;;
    h) usage; exit 0 ;;
    :) die "option -$OPTARG needs a value" ;;
    *) usage >&2; exit 2 ;;
  esac
done
shift $((OPTIND - 1))
[[ $# -ge 1 ]] || { usage >&2; exit 2; }
[[ $days =~ ^[1-9][0-9]*$ ]] || die "DAYS must be a positive integer, not '$days'"
command -v openssl >/dev/null || die "openssl not found"

# Build the subjectAltName list: IP:... for addresses, DNS:... for host names.
san=""
for name in "$@"; do
  if [[ $name =~ ^[0-9]{1,3}(\.[0-9]{1,3}){3}$ ]]; then
    IFS=. read -r a b c d <<<"$name"
    for octet in "$a" "$b" "$c" "$d"; do
      (( 10#$octet <= 255 )) || die "'$name' is not a valid IPv4 address"
    done
    entry="IP:$name"
  elif [[ $name == *:* ]]; then
    [[ $name =~ ^[0-9A-Fa-f:.]+$ ]] || die "'$name' is not a valid IPv6 address (no brackets, no zone)"
    entry="IP:$name"
  elif [[ $name =~ ^(\*\.)?[A-Za-z0-9]([A-Za-z0-9-]*[A-Za-z0-9])?(\.[A-Za-z0-9]([A-Za-z0-9-]*[A-Za-z0-9])?)*$ ]]; then
    entry="DNS:$name"
  else
    die "'$name' is neither a host name nor an IP address"
  fi
  san+="${san:+,}$entry"
done
cn=$1

mkdir -p -- "$outdir"
cd -- "$outdir"
umask 077   # keys are created readable by their owner only

if [[ $force -eq 0 ]]; then
  for f in server.pem server.key; do
    [[ ! -e $f ]] || die "$outdir/$f exists; use -f to replace it"
  done
fi

tmp=$(mktemp -d)
trap 'rm -rf -- "$tmp"' EXIT
# Run an openssl command; show its chatter only when it fails.
quiet() { "$@" 2>"$tmp/err" || { cat "$tmp/err" >&2; die "failed: $*"; }; }

# 1. The certificate authority (reused when present).
if [[ -e ca.pem || -e ca.key ]]; then
  [[ -e ca.pem && -e ca.key ]] || die "found only one of ca.pem and ca.key in $outdir"
  echo "Reusing the CA in $outdir/ca.pem"
else
  openssl ecparam -name prime256v1 -genkey -noout -out ca.key
  cat >"$tmp/ca.ext" <<'EOF'
basicConstraints = critical, CA:TRUE, pathlen:0
keyUsage = critical, keyCertSign, cRLSign
subjectKeyIdentifier = hash
EOF
  openssl req -new -key ca.key -subj "/CN=matoptd private CA" -out "$tmp/ca.csr"
  quiet openssl x509 -req -in "$tmp/ca.csr" -signkey ca.key -days 3650 -sha256 \
    -set_serial "0x$(openssl rand -hex 16)" -extfile "$tmp/ca.ext" -out ca.pem
  chmod 644 ca.pem
  echo "Created a new CA: $outdir/ca.pem (certificate), $outdir/ca.key (its private key)"
fi

# 2. The server key and certificate, signed by the CA.
openssl ecparam -name prime256v1 -genkey -noout -out "$tmp/server.key"
openssl req -new -key "$tmp/server.key" -subj "/CN=$cn" -out "$tmp/server.csr"
cat >"$tmp/server.ext" <<EOF
basicConstraints = critical, CA:FALSE
keyUsage = critical, digitalSignature
extendedKeyUsage = serverAuth
subjectKeyIdentifier = hash
authorityKeyIdentifier = keyid, issuer
subjectAltName = $san
EOF
quiet openssl x509 -req -in "$tmp/server.csr" -CA ca.pem -CAkey ca.key -days "$days" -sha256 \
  -set_serial "0x$(openssl rand -hex 16)" -extfile "$tmp/server.ext" -out "$tmp/server.pem"
openssl verify -CAfile ca.pem "$tmp/server.pem" >/dev/null || die "the new certificate does not verify"
mv -f -- "$tmp/server.key" server.key
mv -f -- "$tmp/server.pem" server.pem
chmod 644 server.pem

cat <<EOF

Server certificate for ${san//,/, } (valid $days days). Files in $(pwd):

  ca.pem      -> every client: --tls-ca /path/to/ca.pem or MATOPT_TLS_CA=/path/to/ca.pem
                 (and grpcurl -cacert ca.pem). Not secret.
  server.pem  -> the daemon: /etc/matoptd/server.pem (--tls-cert)
  server.key  -> the daemon: /etc/matoptd/server.key (--tls-key). Secret: owner root,
                 group matopt, mode 0640.
  ca.key      -> nowhere. Keep it private and offline; it is needed only to issue further
                 server certificates from this CA (run this script again in this directory).
EOF
