"""Layer 1, the config: one rule per field (``rules``), native-task term params (``native_task``),
alias hints (``aliases``), the typed schemas and their ConfigStore registration (``schema``), the
composed DictConfig -> RootConfig with every check (``validate``), the users' JSON format
(``json_format/``), where shipped configs live (``paths``).

May import: layer 0 (``common``, ``files``) and ``runtime``; the names a config holds are checked
against the pieces' registries (events, hooks, native tasks, PBT) through lazy imports, the one
exception tests/test_structure.py lists.
"""
