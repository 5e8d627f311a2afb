"""MkDocs hook: the reference pages, generated from the code at every build so that they cannot drift.

- ``reference/cli.md``: every ``radarseg`` command, from its argparse parser (``pipelines.cli.build_parser``);
- ``reference/http-api.md``: every route of the service, from the app's OpenAPI schema (``service.main.create_app``);
- ``reference/settings.md``: every service setting, from ``service.settings.Settings`` (type, default, bounds and
  the comment beside the field in the source);
- ``reference/radar-profile.md``: every key of a radar profile file, from ``radar.profiles.files``'s schema.

The Results page's pictures are the ones the shipped model's evaluation drew beside it (``checkpoints/*.png``,
:data:`RESULT_PICTURES`): added to the site as ``images/results/NAME`` at build, never copied into ``docs/``.

The hook also turns a link to a file outside ``docs/`` (``[x](../models/...)``, which the site cannot serve) into
the path in code, so that pages can point at source files and ``mkdocs build --strict`` still checks every link
between pages.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import json
import os
import re
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
PAGES = {
    "reference/cli.md": "cli_page",
    "reference/http-api.md": "http_api_page",
    "reference/settings.md": "settings_page",
    "reference/radar-profile.md": "radar_profile_page",
}
# The pictures of `radarseg evaluate` on the shipped model (checkpoints/report.md), shown on the Results page.
RESULT_PICTURES = ("pr_curves.png", "confusion_ra.png", "confusion_rd.png", "frame_02550.png", "frame_02999.png")
NOTE = "*Generated from the code at every build of the site (`docs/hooks/reference.py`).*\n"
HELP_WIDTH = "100"
LINK = re.compile(r"(!?)\[([^\]]*)\]\(([^)\s]+)\)")


def on_files(files, config):  # noqa: ANN001, ANN201
    from mkdocs.structure.files import File

    if str(REPO) not in sys.path:
        sys.path.insert(0, str(REPO))
    for uri, builder in PAGES.items():
        files.append(File.generated(config, uri, content=globals()[builder]()))
    for name in RESULT_PICTURES:
        files.append(File.generated(config, f"images/results/{name}", abs_src_path=str(REPO / "checkpoints" / name)))
    return files


def on_page_markdown(markdown, page, config, files):  # noqa: ANN001, ANN201
    docs_dir = Path(config["docs_dir"]).resolve()
    page_dir = (docs_dir / page.file.src_uri).parent

    def outside(match: re.Match) -> str:
        image, text, target = match.groups()
        if image or "://" in target or target.startswith(("#", "mailto:")):
            return match.group(0)
        path = (page_dir / target.split("#")[0]).resolve()
        if docs_dir in path.parents or path == docs_dir:
            return match.group(0)
        shown = path.relative_to(REPO) if REPO in path.parents else target
        return text if text.strip("`") == str(shown) else f"{text} (`{shown}`)"

    return LINK.sub(outside, markdown)


# -- the command line ----------------------------------------------------------------------------------------------

def _commands(parser: argparse.ArgumentParser, words: list[str]):  # noqa: ANN202
    """Every command below ``parser`` with its parser; a job's own parser where the top level only names it."""
    from pipelines.cli import JOBS, job_parser_of

    if len(words) == 2 and words[1] in JOBS:
        parser = job_parser_of(words[1])
    yield words, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                yield from _commands(child, [*words, name])


def cli_page() -> str:
    from pipelines.cli import build_parser

    os.environ["COLUMNS"] = HELP_WIDTH  # argparse wraps at the terminal's width: fixed, so builds are identical
    lines = ["# Command line: `radarseg`", "", NOTE,
             "Every command and option, as `radarseg ... --help` prints it. Every job also runs as "
             "`python -m pipelines.<module>` with the same options; `RADARSEG_SMOKE=1` caps every job's sizes.", ""]
    for words, parser in _commands(build_parser(), ["radarseg"]):
        lines += [f"## `{' '.join(words)}`", "", "```text", parser.format_help().rstrip(), "```", ""]
    return "\n".join(lines)


# -- the HTTP API --------------------------------------------------------------------------------------------------

def _cell(text: object) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def _schema_text(schema: dict) -> str:
    """A JSON schema as a reader says it: ``integer, 0 to 64``, ``one of: a, b``, ``SegmentResponse``."""
    if "$ref" in schema:
        name = schema["$ref"].rsplit("/", 1)[-1]
        return f"[{name}](#{name.lower()})"
    for key in ("anyOf", "oneOf"):
        if key in schema:
            return " or ".join(_schema_text(s) for s in schema[key] if s.get("type") != "null") + (
                " or null" if any(s.get("type") == "null" for s in schema[key]) else "")
    if "allOf" in schema and len(schema["allOf"]) == 1:
        return _schema_text(schema["allOf"][0])
    if "enum" in schema:
        return "one of: " + ", ".join(f"`{v}`" for v in schema["enum"])
    kind = schema.get("type", "any")
    if kind == "array":
        text = f"list of {_schema_text(schema.get('items', {}))}"
    elif kind == "object" and "additionalProperties" in schema and isinstance(schema["additionalProperties"], dict):
        text = f"map of {_schema_text(schema['additionalProperties'])}"
    else:
        text = kind + (f" ({schema['format']})" if "format" in schema else "")
    low = schema.get("minimum", schema.get("exclusiveMinimum"))
    high = schema.get("maximum", schema.get("exclusiveMaximum"))
    if low is not None or high is not None:
        text += f", {'' if low is None else low}{' to ' if low is not None and high is not None else ''}" \
                f"{'at most ' if low is None else ''}{'' if high is None else high}"
    if "maxLength" in schema:
        text += f", at most {schema['maxLength']} characters"
    return text


def _operation(path: str, method: str, operation: dict) -> list[str]:
    lines = [f"## `{method.upper()} {path}`", ""]
    if operation.get("summary"):
        lines += [f"**{operation['summary']}**", ""]
    if operation.get("description"):
        lines += [operation["description"].strip(), ""]
    parameters = operation.get("parameters", [])
    if parameters:
        lines += ["| parameter | in | required | type | default | description |", "|---|---|---|---|---|---|"]
        for p in parameters:
            schema = p.get("schema", {})
            default = f"`{_cell(json.dumps(schema['default']))}`" if "default" in schema else ""
            lines.append(f"| `{p['name']}` | {p['in']} | {'yes' if p.get('required') else 'no'} | "
                         f"{_cell(_schema_text(schema))} | {default} | {_cell(p.get('description', ''))} |")
        lines.append("")
    if "requestBody" in operation:
        kinds = ", ".join(f"`{kind}`" + (f" ({_schema_text(body['schema'])})" if "schema" in body else "")
                          for kind, body in operation["requestBody"].get("content", {}).items())
        lines += [f"Request body: {kinds}.", ""]
    lines += ["| status | answer |", "|---|---|"]
    for status, answer in sorted(operation.get("responses", {}).items()):
        bodies = [_schema_text(body["schema"]) for body in answer.get("content", {}).values()
                  if body.get("schema")]
        shown = f": {bodies[0]}" if bodies and bodies[0] != "any" else ""
        lines.append(f"| {status} | {_cell(answer.get('description', ''))}{_cell(shown)} |")
    return [*lines, ""]


def _schemas(components: dict) -> list[str]:
    """Every named schema of the answers and bodies: a table of its fields."""
    lines = ["## Schemas", "", "The fields of the JSON bodies the routes above take and answer.", ""]
    for name, schema in sorted(components.items()):
        lines += [f"### {name}", ""]
        if schema.get("description"):
            lines += [" ".join(schema["description"].split()), ""]
        if "enum" in schema:
            lines += [_schema_text(schema), ""]
            continue
        required = set(schema.get("required", ()))
        fields = schema.get("properties", {})
        if fields:
            lines += ["| field | type | required | description |", "|---|---|---|---|"]
            for field, spec in fields.items():
                lines.append(f"| `{field}` | {_cell(_schema_text(spec))} | {'yes' if field in required else 'no'} | "
                             f"{_cell(spec.get('description', ''))} |")
            lines.append("")
    return lines


def http_api_page() -> str:
    from service.main import create_app
    from service.settings import Settings

    schema = create_app(Settings()).openapi()
    lines = ["# HTTP API", "", NOTE,
             f"{schema['info']['title']} {schema['info']['version']}: every route, its parameters and every answer "
             "it sends, from the service's OpenAPI schema (`GET /openapi.json` of a running service; `/docs` and "
             "`/redoc` show it interactively), and the fields of every JSON body under "
             "[Schemas](#schemas). The guide is [the service and streams](../guides/service.md).", ""]
    for path, methods in schema["paths"].items():
        for method, operation in methods.items():
            lines += _operation(path, method, operation)
    lines += _schemas(schema.get("components", {}).get("schemas", {}))
    return "\n".join(lines)


# -- the service's settings ----------------------------------------------------------------------------------------

def _field_comments(cls: type) -> dict[str, str]:
    """The comment of each field of ``cls``: on its line, or the comment lines right above it."""
    source = inspect.getsource(cls)
    lines = source.splitlines()
    comments: dict[str, str] = {}
    for node in ast.parse(source).body[0].body:
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            above, row = [], node.lineno - 2
            while row >= 0 and lines[row].strip().startswith("#"):
                above.insert(0, lines[row].strip().lstrip("# "))
                row -= 1
            end = lines[node.end_lineno - 1]
            inline = end.split("  # ", 1)[1] if "  # " in end else ""
            comments[node.target.id] = " ".join(part for part in (" ".join(above), inline) if part)
    return comments


def _type_name(annotation: object) -> str:
    name = annotation.__name__ if isinstance(annotation, type) else str(annotation)
    return re.sub(r"\b(typing|pathlib|pydantic|service\.settings)\.", "", name).replace(" | ", " or ")


def settings_page() -> str:
    from service.settings import Settings

    comments = _field_comments(Settings)
    prefix = Settings.model_config.get("env_prefix", "")
    lines = ["# Service settings", "", NOTE,
             f"Every setting of the service (`service/settings.py`, `Settings`), read from the environment variable "
             f"`{prefix}<NAME>`: scalars as text, lists and mappings as JSON. Values outside the bounds are "
             "refused at start-up with the reason.", "",
             "| variable | type | default | bounds | what |", "|---|---|---|---|---|"]
    for name, field in Settings.model_fields.items():
        default = field.get_default(call_default_factory=True)
        shown = json.dumps(default, default=lambda v: v.model_dump(mode="json") if hasattr(v, "model_dump")
                           else str(v))
        bounds = ", ".join(str(m) for m in field.metadata)
        lines.append(f"| `{prefix}{name.upper()}` | `{_cell(_type_name(field.annotation))}` | `{_cell(shown)}` | "
                     f"{_cell(bounds)} | {_cell(comments.get(name, ''))} |")
    return "\n".join(lines + _environment_rows()) + "\n"


def _environment_rows() -> list[str]:
    """The variables the jobs, models and benchmarks read (``models.environment.Environment``)."""
    from models.environment import Environment

    rows = ["", "## Jobs and models", "",
            "What the command line's jobs, the models and the benchmarks read from the environment "
            "(`models/environment.py`, `Environment`; the service gives the models' ones from its settings above).",
            "", "| variable | default | what |", "|---|---|---|"]
    for field in dataclasses.fields(Environment):
        rows.append(f"| `{field.metadata['variable']}` | `{_cell(json.dumps(field.default, default=str))}` | "
                    f"{_cell(field.metadata['what'])} |")
    return rows


# -- radar profile files -------------------------------------------------------------------------------------------

def radar_profile_page() -> str:
    from radar.profiles import files

    example = REPO / "radar" / "profiles" / "presets" / "small.toml"
    lines = ["# Radar profile files", "", NOTE,
             "Every key a radar profile file (TOML or JSON) may hold, from the schema `radar/profiles/files.py` "
             "checks (an unknown key is refused, naming the keys expected). The guide is "
             "[your own radar](../guides/own-radar.md).", "", "```text", inspect.cleandoc(files.__doc__ or ""),
             "```", "", "| table | keys |", "|---|---|"]
    for table, keys in files._SCHEMA.items():
        lines.append(f"| {f'`[{table}]`' if table else '(top level)'} | {', '.join(f'`{k}`' for k in sorted(keys))} |")
    if example.exists():
        lines += ["", f"The built-in `small` preset as a file (`{example.relative_to(REPO)}`):", "", "```toml",
                  example.read_text().rstrip(), "```"]
    return "\n".join(lines) + "\n"
