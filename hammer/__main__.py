"""`python -m hammer ...`: the console script (hammer/entry.py)."""

from hammer.entry import main

main()
