"""Every figure: each takes ``ax``/``axes`` (or makes them) and returns what it drew on."""
