"""The edges: files, the MAVLink link, camera sources. Everything that touches the outside world lives here."""
