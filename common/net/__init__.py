"""The network: the Zenoh transport (transport, the only module of ``common`` that imports
zenoh), authentication and access rules (security), certificates (certs) and who may drive a
robot (provenance).

Imports ``common`` only from net/ and the floors below (config/, contracts/, math/, system/).
"""
