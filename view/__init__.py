"""`hammer view`: the read-only web view of run directories (web_server.py, static/index.html)."""
