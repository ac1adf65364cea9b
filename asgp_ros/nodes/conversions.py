"""ROS message <-> numpy conversions, the only place nodes touch message fields.

Every function here is pure (no node, no publisher) and tested by building messages
directly. Sections are grouped by message family.
"""

from __future__ import annotations
