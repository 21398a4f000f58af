"""The project's ground floor: what every stage uses and nothing of theirs.

``core.checks`` checks settings (every config and every model's settings), ``core.images`` holds the
one tone map and the image files (OpenEXR, PNG), ``core.errors`` the base classes of every error and
``core.variant`` chooses and starts the Mitsuba variant; ``core.notices`` prints the project's warnings
as one plain line on a command line, and ``core.interrupts`` makes Ctrl-C end a command in one line.
It imports no other package of the project
(``tests/test_architecture.py``), and only numpy, OpenEXR, Pillow and the standard library at import
time (mitsuba and drjit are imported by ``core.variant.mitsuba()`` when a stage asks for them).
"""
