"""TI mmWave radars: the mmWave SDK CLI configuration (``.cfg``) as a radar profile, antenna layouts of TI's
evaluation boards, and the DCA1000 / mmWave Studio capture files as ADC frames."""
