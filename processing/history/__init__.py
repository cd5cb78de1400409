"""A surface's history: two visits' images aligned (:mod:`.align`) and their defects matched,
with each crack's growth (:mod:`.changes`)."""
