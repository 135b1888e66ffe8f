"""``matopt scene ...``: load scene bundles, list them, inspect parameters, render previews."""

from __future__ import annotations

from pathlib import Path

import click

from matopt_client import client as mc
from matopt_client import workflow
from matopt_client.cli.output import (deleted, emit_json, fields, json_option, message_dict,
                                      note, number, table, timestamp, uploading, values, warn)
from matopt_client.cli.params import SCENE, Values
from matopt_client.cli.session import Group, connected
from matopt_client.export import download_images
from matopt_api import costs, enums
from matopt_api.v1 import matopt_pb2 as pb


@click.group(cls=Group)
def scene() -> None:
    """Load, inspect and render scenes."""


@scene.command()
@click.argument("scene_xml", metavar="SCENE.xml", required=False)
@click.option("--cornell-box", is_flag=True, help="the built-in Cornell box instead of a file")
@click.option("--set", "overrides", multiple=True, metavar="NAME=VALUE",
              help="an XML <default> value, e.g. --set resx=256 (repeatable)")
@click.option("--name", "display_name", default="", help="display name (default: file name)")
@click.option("--root", type=click.Path(exists=True, file_okay=False),
              help="the folder the scene's file names are relative to (the directory Mitsuba "
                   "was run from) [default: found]")
@json_option
def load(scene_xml: str | None, cornell_box: bool, overrides: tuple[str, ...],
         display_name: str, root: str | None, as_json: bool) -> None:
    """Load a scene; prints its name.

    Uploads SCENE.xml and every file it references, except those the daemon already has.
    A file name is looked up as Mitsuba does: from the folder of the XML naming it, then from
    the root (--root; else the XML's folder, the current directory or a parent folder of the
    XML, the first under which every file is found). '\\' separates folders as '/' does.
    """
    if bool(scene_xml) == cornell_box:
        raise click.UsageError("give either SCENE.xml or --cornell-box")
    if root and cornell_box:
        raise click.UsageError("--root goes with SCENE.xml")
    try:
        defaults = workflow.parse_overrides(overrides)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--set") from None
    if scene_xml:
        # Every file the scene names, found before connecting (the XMLs are read again for
        # the upload): a missing one is the user's to fix whether or not a daemon answers.
        mc.bundle_files(scene_xml, defaults, root)
    created = workflow.create_scene(connected(), scene_xml, defaults, display_name, root,
                                    uploading)
    for warning in created.warnings:
        warn(warning)
    if as_json:
        emit_json(created)
    else:
        click.echo(created.name)


@scene.command("list")
@json_option
def list_scenes(as_json: bool) -> None:
    """List your scenes."""
    client = connected()
    scenes = mc.list_all(client.scenes.ListScenes, pb.ListScenesRequest(), "scenes")
    if as_json:
        emit_json(pb.ListScenesResponse(scenes=scenes))
        return
    table(["NAME", "DISPLAY NAME", "SENSORS", "PARAMETERS", "CREATED"],
          [[s.name, s.display_name, len(s.sensors), s.parameter_count, timestamp(s.create_time)]
           for s in scenes])


@scene.command()
@click.argument("name", metavar="SCENE", type=SCENE)
@json_option
def show(name: str, as_json: bool) -> None:
    """Show a scene's sensors, overrides and files."""
    s = connected().scenes.GetScene(pb.GetSceneRequest(name=name))
    if as_json:
        emit_json(s)
        return
    fields({
        "name": s.name,
        "display name": s.display_name,
        "main file": s.main_file or "(built-in Cornell box)",
        "created": timestamp(s.create_time),
        "parameters": s.parameter_count,
        "media": "yes" if s.has_media else "no",
        "overrides": ", ".join(f"{k}={v}" for k, v in sorted(s.overrides.items())),
        "sensors": ", ".join(f"#{x.index}{f' {x.id}' if x.id else ''} {x.width}x{x.height}"
                             for x in s.sensors),
        "files": len(s.files),
    })
    for warning in s.warnings:
        warn(warning)


@scene.command()
@click.argument("name", metavar="SCENE", type=SCENE)
@json_option
def delete(name: str, as_json: bool) -> None:
    """Delete a scene.

    Its files stay among your blobs: 'matopt blob rm --unused' deletes the blobs no scene or
    job of yours uses any more.
    """
    connected().scenes.DeleteScene(pb.DeleteSceneRequest(name=name))
    deleted([name], as_json)


@scene.command()
@click.argument("name", metavar="SCENE", type=SCENE)
@json_option
def params(name: str, as_json: bool) -> None:
    """List the parameters a job may optimize.

    With their kinds, shapes, values (when short), legal ranges and default learning rates.
    """
    parameters = connected().scenes.ListSceneParameters(
        pb.ListSceneParametersRequest(name=name)).parameters
    if as_json:
        emit_json(pb.ListSceneParametersResponse(parameters=parameters))
        return
    notes = [parameter_note(p) for p in parameters]
    noted = any(notes)
    table(["KEY", "KIND", "SHAPE", "VALUE", "MIN", "MAX", "LR"] + (["NOTE"] if noted else []),
          [[p.key, enums.short_name(pb.ParameterKind, p.kind), "x".join(map(str, p.shape)),
            values(p.value), number(p.min), number(p.max), number(p.default_learning_rate)]
           + ([n] if noted else []) for p, n in zip(parameters, notes)])
    for p in parameters:
        if costs.is_large(p.shape):
            note(costs.parameter_cost(p.key, p.shape))


def parameter_note(p: pb.Parameter) -> str:
    """What to know before selecting it: gradients that need a projective integrator, and the
    memory of a large one (its full cost is printed below the table)."""
    words = ["discontinuous"] if p.discontinuous else []
    if costs.is_large(p.shape):
        size = costs.value_count(p.shape) * costs.DEVICE_BYTES_PER_VALUE
        words.append(f"large: {costs.format_size(size)} to optimize")
    return ", ".join(words)


def parameter_values(client: mc.Client, args) -> list[pb.ParameterValue]:
    """``--set-param`` values as the API wants them; a ``KEY=@file.npy`` is uploaded first."""
    out = []
    for arg in args:
        if arg.npy is not None:
            blob = mc.blob_name(mc.upload_file(client, arg.npy, uploading))
            out.append(pb.ParameterValue(key=arg.key, blob=blob))
        else:
            out.append(pb.ParameterValue(key=arg.key, value=arg.values))
    return out


@scene.command()
@click.argument("name", metavar="SCENE", type=SCENE)
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False),
              help="directory for the images (sensor<i>_render.png / .exr)")
@click.option("--spp", type=int,
              help="samples per pixel [daemon default: 64]")
@click.option("--set-param", "overrides", multiple=True, type=Values(npy=True),
              help="render with this value instead of the scene's: KEY=v1,v2,... or "
                   "KEY=@values.npy (repeatable)")
@click.option("--sensor", "sensors", multiple=True, type=int,
              help="render only this sensor index (repeatable) [default: all]")
@click.option("--seed", type=click.IntRange(0, 2**32 - 1), default=None, help="random seed")
@json_option
def render(name: str, out_dir: str, spp: int | None, overrides, sensors: tuple[int, ...],
           seed: int | None, as_json: bool) -> None:
    """Render a scene and download the images.

    One PNG (for viewing) and one linear EXR per sensor, optionally with parameter values
    changed for this render only.
    """
    client = connected()
    request = pb.RenderSceneRequest(name=name, parameters=parameter_values(client, overrides),
                                    sensors=sensors, seed=seed or 0)
    if spp is not None:
        request.spp = spp
    response = client.scenes.RenderScene(request)
    written = download_images(client, response.images, Path(out_dir))
    if as_json:
        emit_json({**message_dict(response), "files": [str(p) for p in written]})
    else:
        for path in written:
            click.echo(str(path))
