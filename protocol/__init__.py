"""sumoco wire protocol: message types, msgpack codec, key expressions, frames.

Both daemons and any Python client import this package; nothing here imports
``sumo_side`` or ``physics_side``.
"""

from protocol.codec import decode, decode_as, encode
from protocol.errors import ConfigError, ProtocolError, SumocoError
from protocol.keys import Keys
from protocol.messages import (
    SCHEMA_VERSION,
    AgentBatch,
    AgentClass,
    AgentFlag,
    AgentMode,
    CameraPose,
    EgoPose,
    JunctionTable,
    LaneTable,
    PhysicsAgents,
    PhysicsState,
    StaticData,
    StepAck,
    StepMessage,
    SumoStatus,
    TlsLinks,
    TrafficLights,
    VType,
    VCLASS_TO_AGENT_CLASS,
)

__all__ = [
    "SCHEMA_VERSION", "AgentBatch", "AgentClass", "AgentFlag", "AgentMode", "ConfigError",
    "CameraPose", "EgoPose", "JunctionTable", "Keys", "LaneTable", "PhysicsAgents", "PhysicsState",
    "ProtocolError", "StaticData", "StepAck", "StepMessage", "SumoStatus", "SumocoError", "TlsLinks", "TrafficLights",
    "VType", "VCLASS_TO_AGENT_CLASS", "decode", "decode_as", "encode",
]
