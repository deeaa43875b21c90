"""The LED board: wire protocol, serial client, emulator on a pseudo-terminal, back-off."""
