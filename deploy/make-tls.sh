#!/usr/bin/env bash
# Makes mutual-TLS material for a learner and its actors: a CA, the learner's certificate and
# one per actor, all X.509 v3 with the extensions rustls requires (v1 certificates are
# rejected). Keys are P-256 ECDSA.
#
# The subject common name (CN) is the identity the learner's access-control policy checks
# (learner/src/service/access_control.rs, names in proto/src/identity.rs): actor i's
# certificate has CN=crawler-actor-<i> and may speak only as actor i (ids 0..999); evaluator
# j's CN=crawler-evaluator-<j> (ids 1000..1999, apart from the actors' since both use the
# stats and status keys); the observer certificate (read-only monitoring) CN=crawler-observer.
# An actor started with --id auto takes the id its certificate names. One certificate per
# actor process: two processes with one certificate would be one actor to the learner.
#
# Usage: deploy/make-tls.sh OUT_DIR LEARNER_HOST [ACTORS] [EVALUATORS]
#   LEARNER_HOST: the name or IP actors use to reach the learner (goes in its subjectAltName)
#   ACTORS:       how many actor certificates to make, ids 0..ACTORS-1 (default 4, at most 1000)
#   EVALUATORS:   how many evaluator certificates, ids 1000.. (default 1, at most 1000)
# Produces OUT_DIR/ca.pem, learner.{pem,key}, actor-<i>.{pem,key}, evaluator-<j>.{pem,key},
# observer.{pem,key}. Keep ca.key private. Rerunning reuses the CA and reissues the others.
set -euo pipefail
out="${1:?usage: make-tls.sh OUT_DIR LEARNER_HOST [ACTORS]}"
host="${2:?usage: make-tls.sh OUT_DIR LEARNER_HOST [ACTORS]}"
actors="${3:-4}"
evaluators="${4:-1}"
for count in "$actors" "$evaluators"; do
  if ! [[ "$count" =~ ^[0-9]+$ ]] || ((count > 1000)); then
    echo "error: ACTORS and EVALUATORS must be whole numbers in 0..1000 (certified ids: actors 0..999, evaluators 1000..1999); got $count" >&2
    exit 2
  fi
done
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
  issue "actor-$i" "crawler-actor-$i" "clientAuth" "DNS:crawler-actor-$i"
done
for ((j = 1000; j < 1000 + evaluators; j++)); do
  issue "evaluator-$j" "crawler-evaluator-$j" "clientAuth" "DNS:crawler-evaluator-$j"
done
issue observer "crawler-observer" "clientAuth" "DNS:crawler-observer"
chmod 644 ./*.pem
echo "TLS material in $(pwd): ca.pem, learner.{pem,key}, actor-0..$((actors - 1)).{pem,key}, evaluator-1000..$((999 + evaluators)).{pem,key}, observer.{pem,key}" >&2
