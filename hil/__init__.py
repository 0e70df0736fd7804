"""Hardware in the loop: the pneumatic plant model, the simavr harness and the test bench."""
