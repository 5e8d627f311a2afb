"""TI mmWave SDK CLI configurations (``.cfg``): one command per line, ``%`` starts a comment.

The commands that fix the radar are read (argument orders from the mmWave SDK user guide's CLI section):

- ``channelCfg <rxChannelEn> <txChannelEn> <cascading>``: enable masks (bit i = RX i / TX i);
- ``adcCfg <numADCBits> <adcOutputFmt>``: 0/1/2 = 12/14/16 bits; 0 real, 1 complex 1x, 2 complex 2x;
- ``adcbufCfg <subFrameIdx> <adcOutputFmt> <SampleSwap> <ChanInterleave> <ChirpThreshold>`` (xWR14xx's SDK: without
  subFrameIdx): 0 complex / 1 real; 0 I in LSB, Q in MSB / 1 Q in LSB, I in MSB; 0 interleaved / 1 not;
- ``profileCfg <profileId> <startFreq GHz> <idleTime us> <adcStartTime us> <rampEndTime us> <txOutPower>
  <txPhaseShifter> <freqSlopeConst MHz/us> <txStartTime us> <numAdcSamples> <digOutSampleRate ksps>
  <hpfCornerFreq1> <hpfCornerFreq2> <rxGain>``;
- ``chirpCfg <startIdx> <endIdx> <profileId> <startFreqVar> <freqSlopeVar> <idleTimeVar> <adcStartTimeVar>
  <txEnable>``: the chirp table;
- ``frameCfg <chirpStartIdx> <chirpEndIdx> <numLoops> <numFrames> <framePeriodicity ms> <triggerSelect>
  <frameTriggerDelay>``: one loop fires chirps start..end, in that order: the TDM order;
- ``compRangeBiasAndRxChanPhase <rangeBias m> <Re> <Im> ...``: one (re, im) per virtual antenna, in the order the
  chirps fire (TX-major), then RX.

Refused, naming the command: BPM-MIMO (``bpmCfg`` enabled), advanced frames (``dfeDataOutputMode 3``,
``advFrameCfg``), sub-frames (``subFrameCfg``), cascading, chirps of more than one profile, a chirp enabling two TX at
once (or none), a TX firing twice in a loop, per-chirp variations. The rest of the processing chain's commands (CFAR,
GUI, clutter removal, ...) say nothing about the ADC: ignored and listed; unknown commands too. A configuration that
cannot be read names its unknown commands in the error, with the known command each is likely a misspelling of
(``profileCgf``: did you mean ``profileCfg``?).
"""

from __future__ import annotations

import difflib
import math
from dataclasses import dataclass, field
from pathlib import Path

from radar.errors import UserError
from radar.profiles.limits import MAX_BINS, PHYSICAL_BOUNDS

ADC_BITS = {0: 12, 1: 14, 2: 16}
ADC_FORMATS = {0: "real", 1: "complex 1x", 2: "complex 2x"}
ARGUMENT_COUNTS = {"channelCfg": (3, 5), "adcCfg": (2, 2), "adcbufCfg": (4, 5), "profileCfg": (14, 14),
                   "chirpCfg": (8, 8), "frameCfg": (7, 7), "dfeDataOutputMode": (1, 1), "bpmCfg": (2, 4)}
IGNORED = frozenset({
    "sensorStop", "sensorStart", "flushCfg", "lowPower", "guiMonitor", "cfarCfg", "multiObjBeamForming",
    "clutterRemoval", "calibDcRangeSig", "extendedMaxVelocity", "lvdsStreamCfg", "measureRangeBiasAndRxChanPhase",
    "CQRxSatMonitor", "CQSigImgMonitor", "analogMonitor", "aoaFovCfg", "cfarFovCfg", "calibData", "peakGrouping",
    "nearFieldCfg", "compressionCfg", "antGeometryCfg", "adcDataDitherCfg", "staticBoundaryBox", "boundaryBox",
    "gatingParam", "stateParam", "allocationParam", "maxAcceleration", "trackingCfg", "presenceBoundaryBox",
    "sensorPosition", "bpmCfg", "dfeDataOutputMode", "idlePowerDown", "procChainCfg", "intfMitigCfg"})
REFUSED = {"advFrameCfg": "advanced frames", "subFrameCfg": "sub-frames"}
MAX_CHIRP_INDEX = 511  # the chirp table's last entry (512 chirps, mmWave SDK)
MAX_LOOPS = 255  # frameCfg numLoops (mmWave SDK: 1 to 255)
MAX_CHANNEL_MASK = 0xFFFF  # channelCfg enable masks: 16 channels (one chip has 4 RX and 3 or 4 TX)
# TI's units -> SI, for the physical bounds of radar.profiles.limits
TI_UNITS = {"startFreq": ("carrier_hz", 1e9, "GHz"), "freqSlopeConst": ("slope_hz_per_s", 1e12, "MHz/us"),
            "digOutSampleRate": ("sample_rate_hz", 1e3, "ksps")}
READ = frozenset({"channelCfg", "adcCfg", "adcbufCfg", "profileCfg", "chirpCfg", "frameCfg",
                  "compRangeBiasAndRxChanPhase"})
"""The commands that describe the radar (read into the profile)."""


class TiConfigError(UserError):
    """A TI configuration that is malformed or describes what a radar profile cannot represent."""


@dataclass(frozen=True)
class TiProfile:
    """One ``profileCfg``, in TI's units."""

    profile_id: int
    start_freq_ghz: float
    idle_time_us: float
    adc_start_time_us: float
    ramp_end_time_us: float
    slope_mhz_per_us: float
    tx_start_time_us: float
    samples: int
    sample_rate_ksps: float


@dataclass(frozen=True)
class TiConfig:
    """What a ``.cfg`` says about the radar: enabled antennas, ADC, the one chirp profile, the TDM order and frame."""

    rx_channels: tuple[int, ...]  # enabled RX, by number
    tx_fired: tuple[int, ...]  # TX by number in the order one loop fires them (the TDM order)
    adc_bits: int
    adc_format: str  # "real", "complex 1x", "complex 2x"
    sample_swap: int  # adcbufCfg SampleSwap: 0 I in LSB, Q in MSB; 1 Q in LSB, I in MSB
    profile: TiProfile
    loops: int  # chirp loops (cycles) per frame
    frame_period_ms: float
    range_bias_m: float | None = None
    channel_coefficients: tuple[complex, ...] = ()  # as stated, in the SDK's virtual antenna order
    ignored: tuple[str, ...] = ()  # commands read and ignored (processing chain, monitors, ...)
    unknown: tuple[str, ...] = ()  # commands this parser does not know
    notes: tuple[str, ...] = field(default=())

    @property
    def real_adc(self) -> bool:
        return self.adc_format == "real"


def _numbers(words: list[str], where: str) -> list[float]:
    try:
        values = [float(w) for w in words]
    except ValueError:
        raise TiConfigError(f"{where}: expected numbers, got {' '.join(words)!r}") from None
    if not all(math.isfinite(v) for v in values):
        raise TiConfigError(f"{where}: numbers must be finite, got {' '.join(words)!r}")
    return values


def _int(value: float, where: str, name: str, low: int | None = None, high: int | None = None,
         what: str = "") -> int:
    """``value`` as a whole number, within [low, high] when given (checked before it counts or sizes anything)."""
    if value != int(value):
        raise TiConfigError(f"{where}: {name} must be a whole number, got {value:g}")
    if (low is not None and value < low) or (high is not None and value > high):
        shown = f"{int(value)}" if abs(value) < 1e18 else f"{value:g}"
        raise TiConfigError(f"{where}: {name} = {shown} is out of bounds: {what or 'a whole number'} in [{low}, "
                            f"{high}]")
    return int(value)


def _physical(value: float, where: str, name: str) -> float:
    """A profileCfg quantity in TI's units, within radar.profiles.limits' physical bounds."""
    key, scale, unit = TI_UNITS[name]
    low, high, described = PHYSICAL_BOUNDS[("chirp", key)]
    if not low <= abs(value) * scale <= high:
        raise TiConfigError(f"{where}: {name} = {value:g} {unit} is out of bounds: {described}")
    return value


def _bits(mask: int) -> tuple[int, ...]:
    return tuple(i for i in range(mask.bit_length()) if mask >> i & 1)


def read_commands(text: str, source: str) -> list[tuple[str, str, list[float]]]:
    """(where, command, numeric arguments) of every command line; ``%`` comments and blank lines skipped."""
    commands = []
    for number, line in enumerate(text.splitlines(), start=1):
        words = line.split("%", 1)[0].split()
        if not words:
            continue
        where, name = f"{source}:{number}: {words[0]}", words[0]
        if name in REFUSED:
            raise TiConfigError(f"{where}: {REFUSED[name]} cannot be represented by one radar profile")
        if name in ARGUMENT_COUNTS or name == "compRangeBiasAndRxChanPhase":
            lo, hi = ARGUMENT_COUNTS.get(name, (3, 10_000))
            if not lo <= len(words) - 1 <= hi:
                expected = f"{lo}" if lo == hi else f"{lo} to {hi}"
                raise TiConfigError(f"{where} takes {expected} arguments, got {len(words) - 1}")
            commands.append((where, name, _numbers(words[1:], where)))
        else:
            commands.append((where, name, []))
    return commands


def _profile(where: str, v: list[float]) -> TiProfile:
    samples = _int(v[9], where, "numAdcSamples", 1, MAX_BINS, "ADC samples per chirp")
    if v[10] <= 0 or v[1] <= 0:
        raise TiConfigError(f"{where}: digOutSampleRate and startFreq must be > 0")
    for index, name in ((1, "startFreq"), (7, "freqSlopeConst"), (10, "digOutSampleRate")):
        _physical(v[index], where, name)
    return TiProfile(_int(v[0], where, "profileId"), v[1], v[2], v[3], v[4], v[7], v[8], samples, v[10])


def _check_refusals(commands: list[tuple[str, str, list[float]]]) -> None:
    for where, name, args in commands:
        if name == "dfeDataOutputMode" and args[0] == 3:
            raise TiConfigError(f"{where} 3: advanced frames cannot be represented by one radar profile")
        if name == "bpmCfg" and len(args) >= 2 and args[1] != 0:
            raise TiConfigError(f"{where}: BPM-MIMO (binary phase modulation across TX) is not supported; only "
                                f"TDM-MIMO (bpmCfg ... 0)")
        if name == "channelCfg" and args[2] != 0:
            raise TiConfigError(f"{where}: cascading ({args[2]:g}) is not supported; a single chip only")


def _last(commands: list[tuple[str, str, list[float]]], name: str, source: str) -> tuple[str, list[float]]:
    found = [(where, args) for where, command, args in commands if command == name]
    if not found:
        raise TiConfigError(f"{source}: no {name} command (needed to describe the radar)")
    return found[-1]


def _tdm_order(commands, frame_where: str, frame: list[float], enabled_tx: tuple[int, ...],
               profiles: dict[int, TiProfile]) -> tuple[tuple[int, ...], TiProfile]:
    """(TX fired per chirp of one loop, the one profile those chirps use) from the chirp table and frameCfg."""
    table: dict[int, tuple[str, list[float]]] = {}
    for where, name, args in commands:
        if name == "chirpCfg":
            first = _int(args[0], where, "startIdx", 0, MAX_CHIRP_INDEX, "a chirp index")
            if args[1] < first:
                raise TiConfigError(f"{where}: endIdx = {args[1]:.0f} is out of bounds: at least startIdx {first}")
            for index in range(first, _int(args[1], where, "endIdx", first, MAX_CHIRP_INDEX, "a chirp index") + 1):
                table[index] = (where, args)
    start = _int(frame[0], frame_where, "chirpStartIdx", 0, MAX_CHIRP_INDEX, "a chirp index")
    end = _int(frame[1], frame_where, "chirpEndIdx", start, MAX_CHIRP_INDEX, "a chirp index from chirpStartIdx")
    fired, used_profiles = [], set()
    for index in range(start, end + 1):
        if index not in table:
            raise TiConfigError(f"{frame_where}: chirp {index} of the frame has no chirpCfg")
        where, args = table[index]
        if any(args[3:7]):
            raise TiConfigError(f"{where}: per-chirp variations (start frequency, slope, idle, ADC start) are not "
                                f"represented; they must be 0")
        tx = _bits(_int(args[7], where, "txEnable"))
        if len(tx) != 1:
            raise TiConfigError(f"{where}: chirp {index} enables TX {list(tx)}; TDM-MIMO needs exactly one TX per "
                                f"chirp")
        if tx[0] not in enabled_tx:
            raise TiConfigError(f"{where}: chirp {index} fires TX{tx[0]}, which channelCfg does not enable")
        if tx[0] in fired:
            raise TiConfigError(f"{where}: TX{tx[0]} fires twice in one loop (chirps {start}..{end}); a loop must fire "
                                f"each TX once")
        fired.append(tx[0])
        used_profiles.add(_int(args[2], where, "profileId"))
    if len(used_profiles) != 1:
        raise TiConfigError(f"{frame_where}: the frame's chirps use profiles {sorted(used_profiles)}; one profile only")
    profile_id = used_profiles.pop()
    if profile_id not in profiles:
        raise TiConfigError(f"{frame_where}: the frame's chirps use profile {profile_id}, which no profileCfg defines")
    return tuple(fired), profiles[profile_id]


def unknown_commands(commands: list[tuple[str, str, list[float]]]) -> list[str]:
    """Each command neither read nor ignored, where it is, and the known command it likely misspells:
    ``"cfg:5: profileCgf (did you mean profileCfg?)"``."""
    known = sorted(READ | IGNORED | set(REFUSED))
    found = []
    for where, name, _ in commands:
        if name in READ or name in IGNORED:
            continue
        close = difflib.get_close_matches(name, known, n=1, cutoff=0.75)
        found.append(f"{where}" + (f" (did you mean {close[0]}?)" if close else ""))
    return found


def parse_cfg(text: str, source: str = "cfg") -> TiConfig:
    """A :class:`TiConfig` from the text of a ``.cfg``; :class:`TiConfigError` naming the line when it cannot be one,
    and the file's unknown commands (a misspelled ``profileCgf`` is why no ``profileCfg`` defines the profile)."""
    commands = read_commands(text, source)
    try:
        return _parse_commands(commands, source)
    except TiConfigError as error:
        unknown = unknown_commands(commands)
        if not unknown:
            raise
        raise TiConfigError(f"{error}; the file has unknown command(s): {'; '.join(unknown)}") from None


def _parse_commands(commands: list[tuple[str, str, list[float]]], source: str) -> TiConfig:
    _check_refusals(commands)
    channel_where, channel = _last(commands, "channelCfg", source)
    adc_where, adc = _last(commands, "adcCfg", source)
    adc_bits = ADC_BITS[_int(adc[0], adc_where, "numADCBits", 0, 2, "0/1/2 (12/14/16 bits)")]
    adc_format = ADC_FORMATS[_int(adc[1], adc_where, "adcOutputFmt", 0, 2, "0/1/2 (real, complex 1x, 2x)")]
    sample_swap, notes = 1, []
    buffers = [(where, args) for where, name, args in commands if name == "adcbufCfg"]
    if buffers:
        where, args = buffers[-1]
        args = args[-4:]  # the xWR14xx SDK's form has no subFrameIdx
        if (args[0] == 1) != (adc_format == "real"):
            raise TiConfigError(f"{where}: adcOutputFmt {args[0]:g} ({'real' if args[0] == 1 else 'complex'}) "
                                f"contradicts adcCfg's {adc_format} ADC")
        sample_swap = int(args[1])
    profiles = {}
    for where, name, args in commands:
        if name == "profileCfg":
            profile = _profile(where, args)
            profiles[profile.profile_id] = profile
    frame_where, frame = _last(commands, "frameCfg", source)
    rx = _bits(_int(channel[0], channel_where, "rxChannelEn", 0, MAX_CHANNEL_MASK, "an enable mask"))
    enabled_tx = _bits(_int(channel[1], channel_where, "txChannelEn", 0, MAX_CHANNEL_MASK, "an enable mask"))
    if not rx or not enabled_tx:
        raise TiConfigError(f"{source}: channelCfg enables no RX or no TX")
    fired, profile = _tdm_order(commands, frame_where, frame, enabled_tx, profiles)
    unused = sorted(set(enabled_tx) - set(fired))
    if unused:
        notes.append(f"TX {unused} enabled by channelCfg but fired by no chirp of the frame")
    bias, coefficients = _calibration(commands)
    ignored = sorted({name for _, name, _ in commands if name in IGNORED})
    unknown = sorted({name for _, name, _ in commands if name not in IGNORED and name not in READ})
    loops = _int(frame[2], frame_where, "numLoops", 1, MAX_LOOPS, "chirp loops per frame")
    low, high, described = PHYSICAL_BOUNDS[("", "frame_rate_hz")]
    if not 1e3 / high <= frame[4] <= 1e3 / low:
        raise TiConfigError(f"{frame_where}: framePeriodicity = {frame[4]:g} ms is out of bounds: {1e3 / high:g} to "
                            f"{1e3 / low:g} ms ({described})")
    return TiConfig(rx, fired, adc_bits, adc_format, sample_swap, profile, loops, frame[4], bias,
                    coefficients, tuple(ignored), tuple(unknown), tuple(notes))


def _calibration(commands) -> tuple[float | None, tuple[complex, ...]]:
    found = [(where, args) for where, name, args in commands if name == "compRangeBiasAndRxChanPhase"]
    if not found:
        return None, ()
    where, args = found[-1]
    if len(args) % 2 != 1:
        raise TiConfigError(f"{where}: expected a range bias, then (re, im) pairs; got {len(args)} numbers")
    return args[0], tuple(complex(args[i], args[i + 1]) for i in range(1, len(args), 2))


def load_cfg(path: str | Path) -> TiConfig:
    """:func:`parse_cfg` of a file."""
    path = Path(path)
    if not path.is_file():
        raise TiConfigError(f"{path}: no such file")
    if path.stat().st_size > 1_000_000:
        raise TiConfigError(f"{path}: {path.stat().st_size} bytes; a TI .cfg is a few kB of text")
    try:
        text = path.read_text()
    except UnicodeDecodeError:
        raise TiConfigError(f"{path}: not a text file (a TI .cfg holds one CLI command per line)") from None
    return parse_cfg(text, str(path))
