"""MobiNet: NetWatch tasks answered from the robot's network subsystem over SNMP.

`MobiNetControl` is the plugin; `MobiNetResource` owns the SNMP thread; `NetworkSource`
is the one interface a network subsystem is read through (`SnmpSource` speaks SNMPv2c).
"""

from erni.plugins.mobinet.control import MobiNetControl
from erni.plugins.mobinet.resource import MobiNetResource, NetView, NetworkSource, SourceError
from erni.plugins.mobinet.snmp import SnmpSource

__all__ = ["MobiNetControl", "MobiNetResource", "NetView", "NetworkSource", "SnmpSource",
           "SourceError"]
