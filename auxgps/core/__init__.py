"""The pure core: arrays and dataclasses in, dataclasses out. No files, sockets, clocks or MAVLink here."""
