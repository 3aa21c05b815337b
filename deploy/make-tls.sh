#!/usr/bin/env bash
# Makes mutual-TLS material for a learner and its actors: a CA, the learner's certificate and
# one per actor, all X.509 v3 with the extensions rustls requires (v1 certificates are
# rejected). Keys are P-256 ECDSA.
#
# The subject common name (CN) is the role the learner's access-control policy checks
# (learner/src/service/access_control.rs): every actor certificate has CN=crawler-actor, the observer
# certificate (read-only monitoring) CN=crawler-observer. Each actor's own name
# (crawler-actor-<i>) is in its subjectAltName and its serial number differs.
#
# Usage: deploy/make-tls.sh OUT_DIR LEARNER_HOST [ACTORS]
#   LEARNER_HOST: the name or IP actors use to reach the learner (goes in its subjectAltName)
#   ACTORS:       how many actor certificates to make (default 4)
# Produces OUT_DIR/ca.pem, learner.{pem,key}, actor-<i>.{pem,key}, observer.{pem,key}.
# Keep ca.key private. Rerunning reuses the CA and reissues the other certificates.
set -euo pipefail
out="${1:?usage: make-tls.sh OUT_DIR LEARNER_HOST [ACTORS]}"
host="${2:?usage: make-tls.sh OUT_DIR LEARNER_HOST [ACTORS]}"
actors="${3:-4}"
days=825
# Keys are private from the moment they exist (chmod after writing would leave a window);
# certificates are made readable below.
umask 077
mkdir -p "$out"
cd "$out"

if [[ "$host" =~ ^[0-9.]+$ ]]; then san="IP:$host,DNS:localhost,IP:127.0.0.1"; else san="DNS:$host,DNS:localhost,IP:127.0.0.1"; fi

new_key() { openssl ecparam -name prime256v1 -genkey -noout -out "$1" 2>/dev/null; chmod 600 "$1"; }

if [ ! -f ca.key ]; then
  new_key ca.key
  openssl req -x509 -new -key ca.key -sha256 -days "$days" -subj "/CN=crawler CA" \
    -addext "basicConstraints=critical,CA:TRUE" \
    -addext "keyUsage=critical,keyCertSign,cRLSign" \
    -addext "subjectKeyIdentifier=hash" -out ca.pem
fi

# issue NAME CN EXTENDED_USAGE SAN
issue() {
  local name="$1" cn="$2" usage="$3" alt="$4"
  new_key "$name.key"
  openssl req -new -key "$name.key" -subj "/CN=$cn" -out "$name.csr"
  cat > "$name.ext" <<EXT
basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature,keyEncipherment
extendedKeyUsage=$usage
subjectKeyIdentifier=hash
authorityKeyIdentifier=keyid,issuer
subjectAltName=$alt
EXT
  openssl x509 -req -in "$name.csr" -CA ca.pem -CAkey ca.key -CAcreateserial -sha256 -days "$days" \
    -extfile "$name.ext" -out "$name.pem" 2>/dev/null
  rm -f "$name.csr" "$name.ext"
}

issue learner "$host" "serverAuth,clientAuth" "$san"
for ((i = 0; i < actors; i++)); do
  issue "actor-$i" "crawler-actor" "clientAuth" "DNS:crawler-actor-$i"
done
issue observer "crawler-observer" "clientAuth" "DNS:crawler-observer"
chmod 644 ./*.pem
echo "TLS material in $(pwd): ca.pem, learner.{pem,key}, actor-0..$((actors - 1)).{pem,key}, observer.{pem,key}" >&2
