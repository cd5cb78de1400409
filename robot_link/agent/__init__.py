"""The on-board agent for a real robot (``steelscan robot``): the MCU over serial, the camera
and ToF through adapters, the station over :mod:`robot_link.client`, safety on board and the
autonomous coverage sweep."""
