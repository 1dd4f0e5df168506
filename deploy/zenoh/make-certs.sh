#!/usr/bin/env bash
# Make a private certificate authority and a router certificate for swimm's TLS configs.
#
#   deploy/zenoh/make-certs.sh OUT_DIR [HOST ...]
#
# OUT_DIR gets ca.pem (give it to every client: root_ca_certificate), ca-key.pem (keep it offline),
# router.pem and router-key.pem (the router's listen_certificate and listen_private_key).
# HOSTs are the names and addresses clients put in their endpoint (tls/HOST:7447); the router certificate
# must name each one, or clients refuse it. Default: localhost 127.0.0.1.
# Each run makes a new CA: re-run it to rotate everything, then redistribute ca.pem.
set -euo pipefail

out=${1:?usage: make-certs.sh OUT_DIR [HOST ...]}
shift
if [ $# -gt 0 ]; then hosts=("$@"); else hosts=(localhost 127.0.0.1); fi
days=${SWIMM_CERT_DAYS:-825}

mkdir -p "$out"
cd "$out"

san=""
for host in "${hosts[@]}"; do
  if [[ $host =~ ^[0-9.]+$ || $host == *:* ]]; then san+="IP:$host,"; else san+="DNS:$host,"; fi
done
san=${san%,}

openssl req -x509 -newkey rsa:2048 -nodes -sha256 -days "$days" \
  -keyout ca-key.pem -out ca.pem -subj "/CN=swimm-ca" \
  -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" 2>/dev/null

openssl req -newkey rsa:2048 -nodes -sha256 -keyout router-key.pem -out router.csr -subj "/CN=${hosts[0]}" 2>/dev/null
openssl x509 -req -in router.csr -CA ca.pem -CAkey ca-key.pem -CAcreateserial -sha256 -days "$days" \
  -out router.pem -extfile <(printf 'subjectAltName=%s\nbasicConstraints=CA:FALSE\nkeyUsage=digitalSignature,keyEncipherment\nextendedKeyUsage=serverAuth,clientAuth\n' "$san") 2>/dev/null
rm -f router.csr ca.srl
chmod 600 ca-key.pem router-key.pem
echo "wrote $out/{ca.pem,ca-key.pem,router.pem,router-key.pem} for ${hosts[*]}"
