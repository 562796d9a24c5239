"""Sweep and evaluation directories read back as data and rendered: tables, figures, escaping."""
