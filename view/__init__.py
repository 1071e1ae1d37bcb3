"""`hammer view`: the read-only web view of run directories (server.py, static/index.html)."""
