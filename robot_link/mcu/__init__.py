"""The serial link between the on-board computer and the robot's microcontroller (MCU):
framing (:mod:`.framing`), packets (:mod:`.packets`) and the host side (:mod:`.link`).
The wire format is documented in docs/robot.md."""
