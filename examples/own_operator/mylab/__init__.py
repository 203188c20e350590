"""An example package of your own operators (see ../README.md)."""
