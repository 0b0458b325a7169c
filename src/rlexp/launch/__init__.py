"""Launch helpers: entry points (``json_entry``: ``train.py --config-json``) and launchers."""
