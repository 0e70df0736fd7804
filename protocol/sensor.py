"""The board's pressure reading in the host's units, from the spec's constants (protocol/spec.toml)."""

from phantom.protocol.messages import CONSTANTS

#: One count of the board's pressure reading (kPa): a ratiometric ADC of ``ADC_FULL_SCALE_COUNTS`` over a sensor
#: that gives ``SENSOR_PERMILLE_PER_KPA`` of its supply per kPa (MPXV7025G over 10 bits: 1 / (0.018 * 1024) =
#: 0.0543 kPa). The board holds a setpoint to about a count.
ADC_COUNT_KPA = 1000.0 / (CONSTANTS["SENSOR_PERMILLE_PER_KPA"] * CONSTANTS["ADC_FULL_SCALE_COUNTS"])
