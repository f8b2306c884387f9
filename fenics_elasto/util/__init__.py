"""Plumbing every layer uses: one-line user errors, the logger, interrupts, memory and time budgets."""
