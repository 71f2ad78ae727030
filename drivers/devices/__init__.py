"""The devices: interfaces (Protocols), links, Modbus, serial ASCII, axes, register map, cameras."""
