"""The wire protocol between host and firmware: message table, frame codec and streaming reader."""
