"""Configuration: the settings tree and the one srl.toml (settings), the command-line flags
(arguments), and Settings -> math objects (assembly).

Imports ``common`` only from config/ and the floors below (contracts/, math/, system/).
"""
