"""The names in softplc's self-signed certificates (HTTPS: security/tls.py; OPC UA: opcua/pki.py).

Owns: the subject (`softplc@HOST`, organisation softplc) and the subject alternative names
(each host as an IP address when it is one, else a DNS name; an OPC UA ApplicationUri first).
Does not know: keys, validity, what the certificate is for.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Iterable

from cryptography import x509
from cryptography.x509.oid import NameOID


def subject(host: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"softplc@{host}"),
                      x509.NameAttribute(NameOID.ORGANIZATION_NAME, "softplc")])


def alt_names(hosts: Iterable[str], uri: str | None = None) -> x509.SubjectAlternativeName:
    names: list[x509.GeneralName] = [x509.UniformResourceIdentifier(uri)] if uri else []
    for host in dict.fromkeys(hosts):
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            names.append(x509.DNSName(host))
    return x509.SubjectAlternativeName(names)
