"""VGG Image Annotator 3 (video annotator) files: read the project JSON and the CSV export, write both.

Project JSON (VIA 3.x ``_via_data.store``): keys ``project`` (``pname``, ``creator``, ``vid_list``),
``config``, ``attribute`` (aid -> ``aname``, ``anchor_id``, ``type``, ``options`` {option_id: text}),
``file`` (fid -> ``fname``), ``view`` (vid -> ``fid_list``) and ``metadata`` (mid -> ``vid``, ``flg``,
``z``, ``xy``, ``av``). A temporal segment has ``z = [start_s, end_s]`` and empty ``xy``; ``z`` with one
value is a still-frame marker; ``av`` maps attribute id -> option id (select/radio) or free text.
Temporal-segment attributes are anchored ``FILE1_Z2_XY0``.

CSV export (VIA 3 "Export -> CSV"): ``#`` comment lines, among them ``# ATTRIBUTE = {json}`` (the
attribute table) and ``# CSV_HEADER = metadata_id,file_list,flags,temporal_coordinates,
spatial_coordinates,metadata``; then one row per metadata whose list/dict columns are JSON text
(RFC 4180 quoted, ``""`` for ``"``).
"""

from __future__ import annotations

import csv
import io
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from midas_cli import __version__
from midas_cli.errors import ConfigError, SessionError
from midas_cli.labels.segments import TimedSegment
from midas_cli.labels.taxonomy import Taxonomy

TEMPORAL_ANCHOR = "FILE1_Z2_XY0"
TYPE_TEXT, TYPE_SELECT = 1, 4
CSV_COLUMNS = ["metadata_id", "file_list", "flags", "temporal_coordinates", "spatial_coordinates", "metadata"]
_VIA_CREATOR = "VGG Image Annotator"
_ANNOTATOR_NAMES = {"annotator", "annotated_by", "annotator_name", "rater"}


@dataclass(frozen=True)
class ViaMetadata:
    """One VIA metadata entry: ``z`` video seconds, ``xy`` region (empty for temporal segments)."""

    mid: str
    vid: str
    z: tuple[float, ...]
    xy: tuple[float, ...]
    av: dict[str, str]


@dataclass
class ViaProject:
    """What both VIA formats carry: attributes, the video file names of each view, metadata."""

    kind: str
    attributes: dict[str, dict[str, Any]]
    view_files: dict[str, list[str]]
    metadata: list[ViaMetadata]
    creator: str = ""


def read_via(path: Path) -> ViaProject:
    """Read a VIA 3 project JSON or CSV export (told apart by content, not by extension)."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise SessionError(f"cannot read VIA file {path}: {exc}") from exc
    if text.lstrip().startswith("{"):
        return parse_via_json(text, str(path))
    return parse_via_csv(text, str(path))


def parse_via_json(text: str, where: str) -> ViaProject:
    """Parse a VIA 3 project file (the JSON VIA saves with "Save project"); a section or entry of the
    wrong JSON type is a SessionError naming it."""
    try:
        store = json.loads(text)
    except json.JSONDecodeError as exc:
        raise SessionError(f"{where} is not valid JSON: {exc}") from exc
    store = _object(store, "the top level", where)
    missing = {"project", "attribute", "file", "view", "metadata"} - set(store)
    if missing:
        raise SessionError(f"{where} is not a VIA 3 project: missing key(s) {', '.join(sorted(missing))}")
    files = {fid: _object(f, f"file {fid!r}", where).get("fname", "")
             for fid, f in _object(store["file"], "'file'", where).items()}
    view_files = {vid: [files.get(str(fid), str(fid)) for fid in _array(_object(v, f"view {vid!r}", where)
                                                                          .get("fid_list", []), "fid_list", where)]
                  for vid, v in _object(store["view"], "'view'", where).items()}
    entries = {mid: _object(m, f"metadata {mid!r}", where)
               for mid, m in _object(store["metadata"], "'metadata'", where).items()}
    metadata = [_metadata(mid, m.get("vid", ""), m.get("z", []), m.get("xy", []), m.get("av", {}), where)
                for mid, m in entries.items()]
    return ViaProject("via-json", _attributes(store["attribute"], where), view_files, metadata,
                      str(_object(store["project"], "'project'", where).get("creator", "")))


def _object(value: Any, what: str, where: str) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise SessionError(f"{where}: {what} must be a JSON object, got {type(value).__name__} (not a VIA 3 file?)")
    return value


def _array(value: Any, what: str, where: str) -> list[Any]:
    if not isinstance(value, list):
        raise SessionError(f"{where}: {what} must be a JSON array, got {type(value).__name__} (not a VIA 3 file?)")
    return value


def _attributes(value: Any, where: str) -> dict[str, dict[str, Any]]:
    """VIA's attribute table, each attribute an object whose ``options`` (if any) map id -> text."""
    attributes = {}
    for aid, attr in _object(value, "'attribute'", where).items():
        attr = dict(_object(attr, f"attribute {aid!r}", where))
        options = _object(attr.get("options") or {}, f"attribute {aid!r} options", where)
        attributes[str(aid)] = {**attr, "options": {str(k): str(v) for k, v in options.items()}}
    return attributes


def parse_via_csv(text: str, where: str) -> ViaProject:
    """Parse a VIA 3 CSV export; the ``# ATTRIBUTE`` line supplies the option tables."""
    attributes: dict[str, dict[str, Any]] | None = None
    header: list[str] | None = None
    body = []
    for line in text.splitlines():
        if line.startswith("# ATTRIBUTE = "):
            attributes = _json_field(line.split("=", 1)[1], "# ATTRIBUTE", where)
        elif line.startswith("# ATTRIBUTES = "):  # older VIA 3.0 exports: aid -> name only, no options
            names = _object(_json_field(line.split("=", 1)[1], "# ATTRIBUTES", where), "# ATTRIBUTES", where)
            attributes = {aid: {"aname": n, "anchor_id": TEMPORAL_ANCHOR, "type": TYPE_TEXT, "options": {}}
                          for aid, n in names.items()}
        elif line.startswith("# CSV_HEADER = "):
            header = [c.strip() for c in line.split("=", 1)[1].split(",") if c.strip()]
        elif line.strip() and not line.startswith("#"):
            body.append(line)
    if header is None or attributes is None:
        raise SessionError(f"{where} is not a VIA 3 CSV export: it needs '# ATTRIBUTE = ...' and "
                           "'# CSV_HEADER = ...' lines (export with VIA's 'Export -> CSV', or give the project JSON)")
    if header[:6] != CSV_COLUMNS:
        raise SessionError(f"{where}: CSV_HEADER {header} is not VIA 3's {CSV_COLUMNS} (the 'temporal segments' "
                           "CSV has no option table: export 'CSV' or use the project JSON)")
    return ViaProject("via-csv", _attributes(attributes, where), *_csv_rows(body, where))


def _csv_rows(body: list[str], where: str) -> tuple[dict[str, list[str]], list[ViaMetadata]]:
    """Rows -> (file names per view, metadata); a row's view id is its metadata id's ``<vid>_`` prefix."""
    view_files: dict[str, list[str]] = {}
    metadata = []
    for number, row in enumerate(csv.reader(io.StringIO("\n".join(body))), start=1):
        if len(row) < 6:
            raise SessionError(f"{where}: data row {number} has {len(row)} fields, expected 6: {row}")
        mid = row[0]
        vid = mid.split("_", 1)[0] if "_" in mid else "1"
        view_files.setdefault(vid, [str(f) for f in _array(_json_field(row[1], "file_list", where), "file_list", where)])
        metadata.append(_metadata(mid, vid, _json_field(row[3], "temporal_coordinates", where),
                                  _json_field(row[4], "spatial_coordinates", where),
                                  _json_field(row[5], "metadata", where), where))
    return view_files, metadata


def _json_field(value: str, column: str, where: str) -> Any:
    try:
        return json.loads(value.strip())
    except json.JSONDecodeError as exc:
        raise SessionError(f"{where}: column {column} is not JSON: {value!r} ({exc})") from exc


def _metadata(mid: str, vid: Any, z: Any, xy: Any, av: Any, where: str) -> ViaMetadata:
    try:
        return ViaMetadata(str(mid), str(vid), tuple(float(v) for v in z), tuple(float(v) for v in xy),
                           {str(k): str(v) for k, v in dict(av).items()})
    except (TypeError, ValueError) as exc:
        raise SessionError(f"{where}: metadata {mid!r} is malformed (z={z!r}, xy={xy!r}, av={av!r})") from exc


def gesture_attribute(project: ViaProject, taxonomy: Taxonomy, wanted: str | None = None) -> str:
    """The id of the temporal-segment attribute holding the gesture: ``wanted`` (id or name) or the only
    temporal attribute, or the only one whose option texts all name gestures of ``taxonomy``."""
    temporal = {aid: a for aid, a in project.attributes.items() if a.get("anchor_id") == TEMPORAL_ANCHOR}
    if wanted is not None:
        for aid, a in project.attributes.items():
            if wanted in (aid, a.get("aname")):
                return aid
        raise ConfigError(f"VIA file has no attribute {wanted!r} (attributes: {_attribute_list(project)})")
    if len(temporal) == 1:
        return next(iter(temporal))
    fitting = [aid for aid, a in temporal.items()
               if a.get("options") and all(taxonomy.resolve(t) for t in a["options"].values())]
    if len(fitting) != 1:
        raise ConfigError(f"cannot tell which VIA attribute holds the gesture (temporal attributes: "
                          f"{_attribute_list(project, temporal)}); pass --attribute ID_OR_NAME")
    return fitting[0]


def _attribute_list(project: ViaProject, only: dict | None = None) -> str:
    chosen = project.attributes if only is None else only
    return ", ".join(f"{aid}={a.get('aname')!r}" for aid, a in chosen.items()) or "none"


def via_segments(project: ViaProject, taxonomy: Taxonomy, attribute: str | None = None,
                 video_file: str | None = None) -> tuple[list[TimedSegment], list[dict[str, Any]]]:
    """The gesture segments of one video: (segments, skipped entries with a reason each).

    Raises ConfigError for an option id the attribute does not define, or option text that names no
    gesture of the taxonomy -- both name the offending id/text and the segment."""
    aid = gesture_attribute(project, taxonomy, attribute)
    vid = _choose_view(project, video_file)
    segments, skipped = [], []
    for m in project.metadata:
        if m.vid != vid:
            continue
        reason = _skip_reason(m, aid)
        if reason:
            skipped.append({"segment": m.mid, "z": list(m.z), "reason": reason})
            continue
        label = _label(project.attributes[aid], aid, m, taxonomy)
        segments.append(TimedSegment(label, m.z[0], m.z[1], m.mid))
    return segments, skipped


def _skip_reason(m: ViaMetadata, aid: str) -> str:
    if m.xy:
        return "spatial region, not a temporal segment"
    if not m.z:
        return "file-level attribute, not a segment"
    if len(m.z) != 2:
        return "still-frame marker (one time), not a segment"
    if m.z[1] <= m.z[0]:
        return "end is not after start"
    if aid not in m.av or m.av[aid] == "":
        return "segment has no gesture value"
    return ""


def _label(attr: dict[str, Any], aid: str, m: ViaMetadata, taxonomy: Taxonomy) -> str:
    value = m.av[aid]
    options = {str(k): str(v) for k, v in (attr.get("options") or {}).items()}
    where = f"segment {m.mid} ({m.z[0]:.3f}-{m.z[1]:.3f} s)"
    if attr.get("type", TYPE_TEXT) != TYPE_TEXT and options:
        if value not in options:
            raise ConfigError(f"unknown option id {value!r} for attribute {attr.get('aname')!r} in {where}; "
                              f"defined options: {', '.join(f'{k}={v}' for k, v in options.items())}")
        value = options[value]
    gesture = taxonomy.resolve(value)
    if gesture is None:
        raise ConfigError(f"{where}: {value!r} names no gesture of taxonomy {taxonomy.name!r} "
                          f"(ids: {', '.join(taxonomy.ids)}); choose the right --taxonomy")
    return gesture


def _choose_view(project: ViaProject, video_file: str | None) -> str:
    used = sorted({m.vid for m in project.metadata})
    if video_file is not None:
        for vid, files in project.view_files.items():
            if any(f == video_file or Path(f).name == video_file for f in files):
                return vid
        raise ConfigError(f"no VIA view shows {video_file!r} (files: {_view_list(project)})")
    if len(used) > 1:
        raise ConfigError(f"the VIA file annotates {len(used)} videos ({_view_list(project)}); "
                          "pick one with --video-file NAME")
    return used[0] if used else ""


def _view_list(project: ViaProject) -> str:
    return ", ".join(f"{vid}: {'+'.join(files)}" for vid, files in project.view_files.items())


def annotators(project: ViaProject) -> list[str]:
    """Annotator names found in the file: values of an attribute named like ``annotator`` and a project
    creator other than VIA's default; empty when none is recorded."""
    aids = [aid for aid, a in project.attributes.items() if str(a.get("aname", "")).casefold() in _ANNOTATOR_NAMES]
    names = {_option_text(project.attributes[aid], m.av[aid]) for aid in aids for m in project.metadata if m.av.get(aid)}
    if project.creator and not project.creator.startswith(_VIA_CREATOR):
        names.add(project.creator)
    return sorted(names)


def _option_text(attr: dict[str, Any], value: str) -> str:
    return str((attr.get("options") or {}).get(value, value))


def via_project(segments: Sequence[TimedSegment], gesture_ids: Sequence[str], video_name: str,
                project_name: str, description: str) -> dict[str, Any]:
    """A VIA 3 project (JSON-able) with one select attribute ``gesture`` whose options are
    ``gesture_ids`` (option id = position) and one temporal segment per entry of ``segments``."""
    option_of = {g: str(i) for i, g in enumerate(gesture_ids)}
    metadata = {f"1_{i:06d}": {"vid": "1", "flg": 0, "z": [round(s.start_s, 5), round(s.end_s, 5)], "xy": [],
                               "av": {"1": option_of[s.label]}} for i, s in enumerate(segments)}
    return {
        "project": {"pid": "__VIA_PROJECT_ID__", "rev": "__VIA_PROJECT_REV_ID__",
                    "rev_timestamp": "__VIA_PROJECT_REV_TIMESTAMP__", "pname": project_name,
                    "creator": f"midas {__version__}", "created": int(time.time() * 1000), "vid_list": ["1"]},
        "config": {"file": {"loc_prefix": {"1": "", "2": "", "3": "", "4": ""}},
                   "ui": {"file_content_align": "center", "file_metadata_editor_visible": True,
                          "spatial_metadata_editor_visible": True, "temporal_segment_metadata_editor_visible": True,
                          "spatial_region_label_attribute_id": "", "gtimeline_visible_row_count": "4"}},
        "attribute": {"1": {"aname": "gesture", "anchor_id": TEMPORAL_ANCHOR, "type": TYPE_SELECT,
                            "desc": description, "options": {v: g for g, v in option_of.items()},
                            "default_option_id": ""}},
        "file": {"1": {"fid": "1", "fname": video_name, "type": 4, "loc": 1, "src": ""}},
        "view": {"1": {"fid_list": ["1"]}},
        "metadata": metadata,
    }


def via_csv_text(project: dict[str, Any]) -> str:
    """The CSV VIA 3 exports for ``project`` (a dict as built by :func:`via_project`)."""
    def cell(value: Any) -> str:
        return '"' + json.dumps(value, separators=(",", ":")).replace('"', '""') + '"'
    lines = ["# Exported using VGG Image Annotator (http://www.robots.ox.ac.uk/~vgg/software/via)",
             f"# ATTRIBUTE = {json.dumps(project['attribute'], separators=(',', ':'))}",
             f"# CSV_HEADER = {','.join(CSV_COLUMNS)}"]
    for mid, m in project["metadata"].items():
        files = [project["file"][fid]["fname"] for fid in project["view"][m["vid"]]["fid_list"]]
        lines.append(",".join([f'"{mid}"', cell(files), str(m["flg"]), cell(m["z"]), cell(m["xy"]), cell(m["av"])]))
    return "\n".join(lines) + "\n"
