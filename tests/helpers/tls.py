"""Looking for a CA's private key among files."""
from __future__ import annotations

from pathlib import Path


def ca_key_files(folder: Path, ca_pem: Path) -> list[str]:
    """The names of the files under ``folder`` that hold the private key of the CA of ``ca_pem``."""
    from cryptography import x509
    from cryptography.hazmat.primitives.serialization import load_pem_private_key

    public = x509.load_pem_x509_certificate(Path(ca_pem).read_bytes()).public_key().public_numbers()
    found = []
    for path in sorted(p for p in Path(folder).rglob("*") if p.is_file()):
        try:
            key = load_pem_private_key(path.read_bytes(), password=None)
        except (ValueError, TypeError):
            continue  # not a private key
        if key.public_key().public_numbers() == public:
            found.append(path.name)
    return found
