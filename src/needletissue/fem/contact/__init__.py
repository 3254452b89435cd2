"""Frictional contact for the FE engine: ``item`` (the FElupe item on the IPC Toolkit) and ``mesh``
(splitting the bonded interfaces of a conforming mesh into contact pairs). See docs/contact.md."""

from needletissue.fem.contact.item import (
    ContactSettings,
    ContactSurface,
    FrictionalContact,
    default_stiffness,
    parse_friction,
    resolve_interfaces,
    unit_pressure,
)
from needletissue.fem.contact.mesh import split_interfaces

__all__ = ["ContactSettings", "ContactSurface", "FrictionalContact", "default_stiffness", "parse_friction",
           "resolve_interfaces", "split_interfaces", "unit_pressure"]
