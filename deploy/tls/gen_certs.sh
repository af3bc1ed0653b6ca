#!/usr/bin/env bash
# Generates the certificates of a TLS deployment: a CA, the router's certificate (SAN 127.0.0.1, localhost and
# the host names given in MFVS_ROUTER_SANS), one client certificate per service (its CN is the service name,
# which the router's access control matches), the operator console's HTTPS certificate (`mfvs console`; server
# use only, SAN 127.0.0.1, localhost and MFVS_CONSOLE_SANS, e.g. "IP:192.168.1.20,DNS:arm-pc.local" for a
# tablet that reaches it by that address), and for tests a rogue CA with a client certificate that claims
# CN=safety and must be rejected.
# Non-interactive. Usage: gen_certs.sh OUTDIR [SERVICE ...]   (default services below)
set -euo pipefail
OUT="${1:?usage: gen_certs.sh OUTDIR [SERVICE ...]}"
shift || true
DAYS=825
SERVICES="${*:-safety robot_sim robot_gateway vision controller operator}"
EXTRA_SANS="${MFVS_ROUTER_SANS:-}"
CONSOLE_SANS="${MFVS_CONSOLE_SANS:-}"
mkdir -p "$OUT"; OUT="$(cd "$OUT" && pwd)"; cd "$OUT"

make_ca () {  # $1 = file prefix, $2 = CN
  openssl req -x509 -newkey rsa:2048 -nodes -sha256 -days 3650 \
    -keyout "$1.key" -out "$1.pem" -subj "/O=mfvs/CN=$2" \
    -addext "basicConstraints=critical,CA:TRUE" \
    -addext "keyUsage=critical,keyCertSign,cRLSign" \
    -addext "subjectKeyIdentifier=hash" 2>/dev/null
}

make_leaf () {  # $1 = name/CN, $2 = CA prefix, $3 = extfile content
  openssl req -new -newkey rsa:2048 -nodes -sha256 \
    -keyout "$1.key" -out "$1.csr" -subj "/O=mfvs/CN=$1" 2>/dev/null
  printf '%s\n' "$3" > "$1.ext"
  openssl x509 -req -in "$1.csr" -CA "$2.pem" -CAkey "$2.key" -CAcreateserial \
    -out "$1.pem" -days "$DAYS" -sha256 -extfile "$1.ext" 2>/dev/null
  rm -f "$1.csr" "$1.ext"
}

SERVER_EXT="basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature,keyEncipherment
extendedKeyUsage=serverAuth,clientAuth
subjectAltName=IP:127.0.0.1,DNS:localhost,DNS:router${EXTRA_SANS:+,$EXTRA_SANS}
authorityKeyIdentifier=keyid,issuer
subjectKeyIdentifier=hash"

# the console's: a web server's certificate, never a zenoh client's (no clientAuth)
CONSOLE_EXT="basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature,keyEncipherment
extendedKeyUsage=serverAuth
subjectAltName=IP:127.0.0.1,DNS:localhost${CONSOLE_SANS:+,$CONSOLE_SANS}
authorityKeyIdentifier=keyid,issuer
subjectKeyIdentifier=hash"

CLIENT_EXT="basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature,keyEncipherment
extendedKeyUsage=clientAuth
authorityKeyIdentifier=keyid,issuer
subjectKeyIdentifier=hash"

# 1. legitimate CA
make_ca ca "mfvs-root-ca"
# 2. router certificate (CN=router, SAN IP:127.0.0.1, DNS:localhost)
make_leaf router ca "$SERVER_EXT"
# 3. one client certificate per service
for s in $SERVICES; do make_leaf "$s" ca "$CLIENT_EXT"; done
# 3b. the operator console's HTTPS certificate
make_leaf console ca "$CONSOLE_EXT"
# 4. rogue CA and a client cert it signed (claims CN=safety!)
make_ca rogue_ca "rogue-ca"
openssl req -new -newkey rsa:2048 -nodes -sha256 -keyout rogue_safety.key -out rogue_safety.csr \
  -subj "/O=mfvs/CN=safety" 2>/dev/null
printf '%s\n' "$CLIENT_EXT" > rogue_safety.ext
openssl x509 -req -in rogue_safety.csr -CA rogue_ca.pem -CAkey rogue_ca.key -CAcreateserial \
  -out rogue_safety.pem -days "$DAYS" -sha256 -extfile rogue_safety.ext 2>/dev/null
rm -f rogue_safety.csr rogue_safety.ext *.srl
chmod 600 ./*.key

# sanity checks
openssl verify -CAfile ca.pem router.pem console.pem $(for s in $SERVICES; do echo "$s.pem"; done)
if openssl verify -CAfile ca.pem rogue_safety.pem >/dev/null 2>&1; then echo "ERROR: rogue verifies!"; exit 1; fi
echo "rogue_safety.pem correctly NOT verifiable with ca.pem"
ls -1 "$OUT"
