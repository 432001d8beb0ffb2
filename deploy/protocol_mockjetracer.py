"""pyserial URL handler for `mockjetracer://`: pyserial imports `<package>.protocol_<scheme>` and uses its `Serial`."""

from deploy.mock_controller import Serial

__all__ = ["Serial"]
