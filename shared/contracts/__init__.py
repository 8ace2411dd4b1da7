"""The wire contract: every bus message (`messages`) and how it travels (`codec`: msgpack + Zenoh encoding)."""
