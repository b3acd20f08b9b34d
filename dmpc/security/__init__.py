"""Transport security: certificates for TLS with mutual authentication, access control
generated from a scenario, and the rules for dropping hostile input (see docs/security.md).

Nothing is imported here: agent processes read their files through ``dmpc.security.files``
without loading the ``cryptography`` package, which only ``dmpc certs`` needs.
"""
