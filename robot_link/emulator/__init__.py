"""The robot's microcontroller, emulated: the simulated robot on a simulated plate behind the
MCU serial protocol on a pseudo-terminal (``steelscan mcu-emulator``)."""
