"""Hostile and careless scene bundles: no file outside the bundle is read, nothing reaches the
renderer that would end it, and what still ends it costs only that request.

Every case goes through a real daemon; a scene that crashes Mitsuba is only ever loaded by the
daemon's worker process, never by this one.
"""

from __future__ import annotations

import hashlib
import math
import os
import struct
import zlib
from pathlib import Path

import grpc
import pytest

import matopt_client.client as mc
from matopt_api import bundle
from matopt_api.v1 import matopt_pb2 as pb

from conftest import Daemon, Stubs
from scenes import QUAD_OBJ, camera, create_scene

# Every message these tests receive is scanned for the daemon's own paths.
pytestmark = pytest.mark.usefixtures("no_server_paths")

QUAD = [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)]


def scene(body: str, head: str = "") -> bytes:
    return f"""<scene version="3.0.0">{head}
    {camera(16)}
    <emitter type="constant"/>
    {body}
</scene>""".encode()


def mesh(kind: str, filename: str) -> str:
    return f"""<shape type="{kind}" id="mesh"><string name="filename" value="{filename}"/>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf></shape>"""


def refused(stubs, files: dict[str, bytes], main: str = "scene.xml", **overrides) -> str:
    """The message of the INVALID_ARGUMENT that creating this scene gets."""
    with pytest.raises(grpc.RpcError) as err:
        create_scene(stubs, files, main, **overrides)
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT, err.value.details()
    return err.value.details()


@pytest.fixture(autouse=True)
def still_serving(stubs):
    yield
    assert stubs.server.GetServerInfo(pb.GetServerInfoRequest()).variant


# -- files outside the bundle -------------------------------------------------------------------

SPECTRUM = b"400 0.2\n550 0.5\n700 0.8\n"


def spectrum_bsdf(filename: str) -> str:
    return f"""<shape type="sphere"><bsdf type="diffuse">
        <spectrum name="reflectance" filename="{filename}"/></bsdf></shape>"""


def test_spectrum_file_outside_the_bundle_is_refused_without_echoing_it(stubs):
    """Mitsuba opens a spectrum's ``filename`` attribute while parsing and quotes the first
    line of a file it cannot read: /etc/passwd's would come back in the error."""
    details = refused(stubs, {"scene.xml": scene(spectrum_bsdf("/etc/passwd"))})
    assert "absolute path '/etc/passwd' (in 'scene.xml')" in details
    assert "root:" not in details
    details = refused(stubs, {"scene.xml": scene('<include filename="parts/inc.xml"/>'),
                              "parts/inc.xml": scene(spectrum_bsdf("../../etc/passwd"))})
    assert "'../../etc/passwd' (in 'parts/inc.xml') leaves the scene bundle" in details


def test_spectrum_file_in_the_bundle_is_uploaded_and_loads(stubs, tmp_path):
    """The client collects a spectrum named by a ``filename`` attribute as it does meshes, and
    the daemon loads the scene."""
    (tmp_path / "spectra").mkdir()
    (tmp_path / "spectra" / "paint.spd").write_bytes(SPECTRUM)
    (tmp_path / "scene.xml").write_bytes(scene(spectrum_bsdf("spectra/paint.spd")))
    main, files = mc.bundle_files(tmp_path / "scene.xml")
    assert sorted(files) == ["scene.xml", "spectra/paint.spd"]
    created = create_scene(stubs, {p: f.read_bytes() for p, f in files.items()}, main)
    assert created.sensors[0].width == 16


def test_path_element_is_refused_with_the_reason(stubs):
    details = refused(stubs, {"scene.xml": scene("", head='<path value="/etc"/>'),
                              "passwd": b"mine"})
    assert "'scene.xml' has a <path> element" in details
    assert "replaced by one from outside" in details


@pytest.mark.parametrize("head,filename,extra,message", [
    ('<default name="f" value="/etc/passwd"/>', "$f", {},
     "absolute path '/etc/passwd' (in 'scene.xml')"),
    # Mitsuba replaces a parameter's name as a plain substring: "$ad" is "$a" then "d".
    ('<default name="a" value="/etc/passw"/>', "$ad", {"$ad": b"decoy"},
     "absolute path '/etc/passwd'"),
    # The daemon turns '\' into '/' in the main XML before Mitsuba sees it: "\$x" is then no
    # longer an escaped, literal '$'.
    ('<default name="x" value="etc/passwd"/>', "\\$x", {"$x": b"decoy"},
     "absolute path '/etc/passwd'"),
    ('<default name="a" value="x"/><default name="b" value="y"/>', "$a$b", {"xy": b"decoy"},
     "may read in more than one way"),
    ('<default name="p" value="../../etc"/>', "$p/passwd", {},
     "'../../etc/passwd' (in 'scene.xml') leaves the scene bundle"),
])
def test_defaults_cannot_smuggle_a_path(stubs, head, filename, extra, message):
    files = {"scene.xml": scene(mesh("obj", filename), head=head), **extra}
    assert message in refused(stubs, files)


def test_a_default_cannot_rename_a_property_into_a_filename(stubs):
    xml = scene('<shape type="obj"><string name="$n" value="/etc/passwd"/></shape>',
                head='<default name="n" value="filename"/>')
    assert "absolute path '/etc/passwd' (in 'scene.xml')" in refused(stubs, {"scene.xml": xml})


def test_meshes_are_checked_as_mitsuba_will_name_them(stubs):
    """A default naming a removed integrator is loaded with its successor's name: the file a
    reference built from it names is the one Mitsuba opens, and that one is checked."""
    files = {"scene.xml": scene(mesh("ply", "$integrator.ply"),
                                head='<default name="integrator" value="prb_reparam"/>'),
             "prb_reparam.ply": ply("ascii", [(0, 1, 2)]),
             "prb_projective.ply": ply("ascii", [(0, 1, 2**31 - 1)])}
    assert "'prb_projective.ply': face 0 refers to vertex 2147483647" in refused(stubs, files)


def test_an_override_cannot_point_a_filename_outside(stubs):
    files = {"scene.xml": scene(mesh("obj", "$m"), head='<default name="m" value="quad.obj"/>'),
             "quad.obj": QUAD_OBJ.encode()}
    details = refused(stubs, files, m="../../../etc/quad.obj")
    assert "'../../../etc/quad.obj' (in 'scene.xml') leaves the scene bundle" in details


@pytest.mark.parametrize("written", ["/etc/hosts", "C:/Windows/win.ini", "a/../../x.obj",
                                     "..\\..\\x.obj", "./../x.obj"])
def test_absolute_and_parent_paths_are_refused_however_written(stubs, written):
    details = refused(stubs, {"scene.xml": scene(mesh("obj", written))})
    assert "is not allowed in a scene bundle" in details or "leaves the scene bundle" in details
    assert "'scene.xml'" in details


LONG = "a" * 300  # bytes: over the 255 a file system takes for one name


@pytest.mark.parametrize("files, main, named", [
    ({f"{LONG}.xml": scene("")}, f"{LONG}.xml", f"{LONG}.xml"),
    ({"scene.xml": scene(mesh("obj", f"{LONG}.obj")), f"{LONG}.obj": QUAD_OBJ.encode()},
     "scene.xml", f"{LONG}.obj"),
    ({"scene.xml": scene(mesh("obj", f"{LONG}/m.obj")), f"{LONG}/m.obj": QUAD_OBJ.encode()},
     "scene.xml", f"{LONG}/m.obj"),
], ids=["main", "mesh", "folder"])
def test_a_name_over_255_bytes_is_refused_naming_the_file(stubs, files, main, named):
    details = refused(stubs, files, main)
    assert f"path '{named}'" in details
    name = max(named.split("/"), key=len)
    assert f"has a file or folder name of {len(name)} bytes" in details
    assert "at most 255" in details


def test_included_file_may_use_windows_separators(stubs):
    """A '\\' separates folders in every XML: the daemon hands Mitsuba a rewritten copy of the
    included file, while the uploaded one stays as it was."""
    shape = mesh("obj", "meshes\\quad.obj")
    files = {"scene.xml": scene('<include filename="parts\\inc.xml"/>'),
             "parts/inc.xml": f'<scene version="3.0.0">{shape}</scene>'.encode(),
             "meshes/quad.obj": QUAD_OBJ.encode()}
    created = create_scene(stubs, files, "scene.xml")
    assert {f.path for f in created.files} == set(files)
    assert {f.sha256 for f in created.files} == {hashlib.sha256(d).hexdigest()
                                                 for d in files.values()}
    keys = [p.key for p in stubs.scenes.ListSceneParameters(
        pb.ListSceneParametersRequest(name=created.name)).parameters]
    assert "mesh.vertex_positions" in keys


def test_plugins_cannot_come_from_the_bundle(stubs):
    """Mitsuba loads 'plugins/<type>.so' through the same lookup as scene files, as code."""
    details = refused(stubs, {"scene.xml": scene('<shape type="../evil"/>')})
    assert "type '../evil'" in details and "letters, digits and '_' only" in details
    details = refused(stubs, {"scene.xml": scene('<shape type="evil"/>'),
                              "plugins/evil.so": b"\x7fELF"})
    assert "'plugins/evil.so'" in details and "shared library" in details
    details = refused(stubs, {"scene.xml": scene(
        '<shape type="sphere"><bsdf type="conductor">'
        '<string name="material" value="../../../../secret"/></bsdf></shape>')})
    assert "material '../../../../secret'" in details


def test_doctype_entities_are_refused(stubs):
    laughs = (b'<?xml version="1.0"?><!DOCTYPE scene [<!ENTITY a "aaaaaaaaaa">'
              + b"".join(f'<!ENTITY {c} "{("&" + p + ";") * 10}">'.encode()
                         for p, c in zip("abcdefgh", "bcdefghi"))
              + b']><scene version="3.0.0"><string name="x" value="&i;"/></scene>')
    external = (b'<!DOCTYPE scene [<!ENTITY e SYSTEM "file:///etc/passwd">]>'
                b'<scene version="3.0.0"><string name="x" value="&e;"/></scene>')
    for xml in (laughs, external):
        details = refused(stubs, {"scene.xml": xml})
        assert "'scene.xml' has a DOCTYPE" in details and "root:" not in details


def test_namespaces_are_refused(stubs):
    """pugixml, which Mitsuba reads with, sees '<string>' where ElementTree sees a namespaced
    tag: a file with namespaces would be checked as one thing and loaded as another."""
    xml = scene('<shape type="obj" xmlns:m="urn:x"><m:string name="filename" value="/etc/x"/>'
                '</shape>')
    assert "uses an XML namespace" in refused(stubs, {"scene.xml": xml})


# -- inputs that crashed the renderer ------------------------------------------------------------

def nested(levels: int) -> bytes:
    return (b'<scene version="3.0.0">' + b"<shape type='sphere'>" * levels
            + b"</shape>" * levels + b"</scene>")


def test_deep_nesting_is_refused_in_every_xml(stubs):
    """20,000 levels in an included file ended the renderer with SIGSEGV; in the main file they
    gave an internal error."""
    details = refused(stubs, {"scene.xml": scene('<include filename="deep.xml"/>'),
                              "deep.xml": nested(20_000)})
    assert f"'deep.xml' nests elements more than {bundle.MAX_DEPTH} levels deep" in details
    details = refused(stubs, {"scene.xml": nested(20_000)})
    assert f"'scene.xml' nests elements more than {bundle.MAX_DEPTH} levels deep" in details
    # Depth adds up across an include: 60 levels around it and 60 inside it are too many.
    wrapped = (b'<scene version="3.0.0">' + b"<shape type='sphere'>" * 59
               + b'<include filename="deep.xml"/>' + b"</shape>" * 59 + b"</scene>")
    details = refused(stubs, {"scene.xml": wrapped, "deep.xml": nested(59)})
    assert "counting the elements around its <include>" in details


def test_include_cycles_are_refused(stubs):
    files = {"scene.xml": scene('<include filename="parts/a.xml"/>'),
             "parts/a.xml": b'<scene version="3.0.0"><include filename="../scene.xml"/></scene>'}
    assert ("'parts/a.xml' includes '../scene.xml', which includes it in turn "
            "(scene.xml -> parts/a.xml -> scene.xml)") in refused(stubs, files)


def ply(fmt: str, faces, index: str = "int", vertices=QUAD) -> bytes:
    head = (f"ply\nformat {fmt} 1.0\nelement vertex {len(vertices)}\nproperty float x\n"
            f"property float y\nproperty float z\nelement face {len(faces)}\n"
            f"property list uchar {index} vertex_indices\nend_header\n").encode()
    if fmt == "ascii":
        return head + "".join(" ".join(map(str, v)) + "\n" for v in vertices).encode() + "".join(
            "3 " + " ".join(map(str, f)) + "\n" for f in faces).encode()
    order = "<" if fmt == "binary_little_endian" else ">"
    code = {"int": "i", "uint": "I", "short": "h", "ushort": "H", "char": "b"}[index]
    return head + b"".join(struct.pack(order + "3f", *v) for v in vertices) + b"".join(
        struct.pack(order + "B" + code * 3, 3, *f) for f in faces)


@pytest.mark.parametrize("fmt,index,bad", [
    ("binary_little_endian", "int", 2**31 - 1),   # ended the renderer with SIGSEGV
    ("ascii", "int", 1000),                      # rendered garbage
    ("binary_big_endian", "int", -5),            # rendered garbage
    ("binary_little_endian", "ushort", 4),
    ("binary_big_endian", "char", -1),
])
def test_ply_faces_past_the_vertices_are_refused(stubs, fmt, index, bad):
    files = {"scene.xml": scene(mesh("ply", "meshes/quad.ply")),
             "meshes/quad.ply": ply(fmt, [(0, 1, 2), (0, 2, bad)], index)}
    details = refused(stubs, files)
    assert (f"'meshes/quad.ply': face 1 refers to vertex {bad}, but the file has 4 vertices"
            in details)


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_valid_ply_loads(stubs, fmt):
    files = {"scene.xml": scene(mesh("ply", "quad.ply")),
             "quad.ply": ply(fmt, [(0, 1, 2), (0, 2, 3)])}
    created = create_scene(stubs, files, "scene.xml")
    keys = [p.key for p in stubs.scenes.ListSceneParameters(
        pb.ListSceneParametersRequest(name=created.name)).parameters]
    assert "mesh.vertex_positions" in keys


def test_a_mesh_read_through_a_default_is_checked_as_its_type_says(stubs):
    """The reader is the shape's type, not the file's extension."""
    files = {"scene.xml": scene(mesh("$kind", "quad.mesh"), head='<default name="kind" '
                                                                 'value="ply"/>'),
             "quad.mesh": ply("ascii", [(0, 1, 7)])}
    assert "'quad.mesh': face 0 refers to vertex 7" in refused(stubs, files)


@pytest.mark.parametrize("faces,message", [
    ("f 1 2 3\nf 1 3 9\n", "'quad.obj' line 6: face refers to vertex 9, but 4 vertices are "
                           "defined before it"),
    ("f 1 2 3\nf -4 -2 -1\n", "'quad.obj' line 6: face uses the relative vertex index -4"),
    ("f 1/1 2/2 0/3\n", "'quad.obj' line 5: face refers to vertex 0"),
])
def test_obj_faces_outside_the_vertices_are_refused(stubs, faces, message):
    obj = "".join(f"v {x} {y} {z}\n" for x, y, z in QUAD) + faces
    files = {"scene.xml": scene(mesh("obj", "quad.obj")), "quad.obj": obj.encode()}
    assert message in refused(stubs, files)


# -- parameter overrides of RenderScene ----------------------------------------------------------

@pytest.fixture(scope="module")
def mesh_scene(stubs) -> tuple[pb.Scene, dict[str, pb.Parameter]]:
    created = create_scene(stubs, {"scene.xml": scene(mesh("obj", "quad.obj")),
                                   "quad.obj": QUAD_OBJ.encode()}, "scene.xml")
    params = stubs.scenes.ListSceneParameters(pb.ListSceneParametersRequest(name=created.name))
    return created, {p.key: p for p in params.parameters}


def render_error(stubs, scene_: pb.Scene, key: str, values) -> grpc.RpcError:
    with pytest.raises(grpc.RpcError) as err:
        stubs.scenes.RenderScene(pb.RenderSceneRequest(
            name=scene_.name, spp=1,
            parameters=[pb.ParameterValue(key=key, value=list(values))]))
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT, err.value.details()
    return err.value.details()


def test_render_overrides_only_listed_parameters(stubs, mesh_scene):
    """A mesh's faces are an integer buffer: set to other numbers, the renderer would index
    memory it does not own. Only what ListSceneParameters lists can be set."""
    created, params = mesh_scene
    assert "mesh.faces" not in params and "mesh.bsdf.reflectance.value" in params
    details = render_error(stubs, created, "mesh.faces", [2**31 - 1] * 6)
    assert "unknown parameter key 'mesh.faces'" in details
    assert "ListSceneParameters lists the parameters that can be set" in details
    details = render_error(stubs, created, "mesh.bsdf.reflectance.valeu", [0.1] * 3)
    assert "did you mean 'mesh.bsdf.reflectance.value'" in details
    details = render_error(stubs, created, "mesh.bsdf.reflectance.value", [0.1, 0.2])
    assert "'mesh.bsdf.reflectance.value': got 2 component(s), expected 3" in details
    details = render_error(stubs, created, "mesh.bsdf.reflectance.value", [0.1, math.nan, 0])
    assert "'mesh.bsdf.reflectance.value': value is not finite" in details
    images = stubs.scenes.RenderScene(pb.RenderSceneRequest(
        name=created.name, spp=1, parameters=[pb.ParameterValue(
            key="mesh.bsdf.reflectance.value", value=[0.1, 0.2, 0.3])])).images
    assert images[0].width == 16


# -- what reaches the user of Mitsuba's messages, and the worker's surroundings -----------------

def test_mitsuba_messages_name_bundle_paths_not_the_daemons(stubs, daemon):
    files = {"scene.xml": scene('<include filename="parts/inc.xml"/>'),
             "parts/inc.xml": scene('<shape type="no_such_plugin"/>')}
    details = refused(stubs, files)
    assert "Mitsuba cannot load 'scene.xml'" in details and "parts/inc.xml" in details
    assert str(daemon.data_dir) not in details and "worker-cache" not in details


def test_worker_runs_in_an_empty_directory_of_its_own(stubs, daemon):
    pid = stubs.server.GetServerInfo(pb.GetServerInfoRequest()).workers[0].pid
    cwd = Path(os.readlink(f"/proc/{pid}/cwd"))
    assert cwd == daemon.data_dir.absolute() / "worker-cache" / "cwd"
    assert list(cwd.iterdir()) == []


def test_file_resolver_is_reset_to_the_scene_before_each_load(tmp_path):
    """A folder left in Mitsuba's global file resolver (the start-up directory, or one a
    ``<path>`` added) no longer serves a scene's relative file names. A harmless scene, so it
    loads in this process."""
    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    from matoptd.engine import scene as scenes
    from matoptd.engine_api import InvalidInput

    outside, inside = tmp_path / "outside", tmp_path / "scenes" / "key"
    outside.mkdir()
    inside.mkdir(parents=True)
    (outside / "stray.obj").write_text(QUAD_OBJ)
    (inside / "scene.xml").write_bytes(scene(mesh("obj", "stray.obj")))
    mi.file_resolver().append(str(outside))
    assert mi.load_file(str(inside / "scene.xml")).shapes()  # found outside, unconfined
    with pytest.raises(InvalidInput) as err:
        scenes.load(inside / "scene.xml", {}, "scene.xml", root=inside)
    assert "stray.obj" in str(err.value) and str(tmp_path) not in str(err.value)
    assert str(outside) not in str(mi.file_resolver())


# -- what still ends the renderer costs that request only ---------------------------------------

def serialized(faces) -> bytes:
    """Mitsuba's own compressed mesh format (version 4), which it reads without checking face
    indices either; not validated before loading, so it stands for whatever else may crash."""
    body = struct.pack("<I", 0x1000) + b"quad\x00" + struct.pack("<QQ", len(QUAD), len(faces))
    body += b"".join(struct.pack("<3f", *v) for v in QUAD)
    body += b"".join(struct.pack("<3I", *f) for f in faces)
    return struct.pack("<HH", 0x041C, 4) + zlib.compress(body)


@pytest.fixture
def own_daemon(tmp_path):
    d = Daemon(tmp_path / "data").start()
    s = Stubs(d.address)
    yield d, s
    s.close()
    d.stop()


def test_a_scene_that_crashes_the_renderer_costs_only_its_request(own_daemon):
    _, stubs = own_daemon
    files = {"scene.xml": scene(mesh("serialized", "quad.serialized")),
             "quad.serialized": serialized([(0, 1, 2), (0, 2, 2**31 - 1)])}
    with pytest.raises(grpc.RpcError) as err:
        create_scene(stubs, files, "scene.xml")
    assert err.value.code() == grpc.StatusCode.INTERNAL
    assert "the renderer process died with SIGSEGV while serving this request" in (
        err.value.details())
    fine = {"scene.xml": scene(mesh("serialized", "quad.serialized")),
            "quad.serialized": serialized([(0, 1, 2), (0, 2, 3)])}
    created = create_scene(stubs, fine, "scene.xml")
    image = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=created.name, spp=1)).images[0]
    assert (image.width, image.height) == (16, 16)


# -- the rules themselves (no daemon) -------------------------------------------------------------

def test_substitution_follows_mitsuba():
    params = {"mesh": "quad", "mesh_lo": "low", "dir": "a/b"}
    assert bundle.substitute("$mesh_lo.ply", params, "x") == "low.ply"     # longest first
    assert bundle.substitute("$mesh_hi.ply", params, "x") == "quad_hi.ply"  # plain substring
    assert bundle.substitute("$dir/\\$mesh", params, "x") == "a/b/$mesh"    # escaped
    with pytest.raises(bundle.BundleError, match="names no parameter"):
        bundle.substitute("$other", params, "x")


def test_includes_are_looked_up_from_the_including_file_first():
    """Mitsuba tries the including file's folder, then the main XML's; a spectrum in an
    included file is looked up from the folder of the file that included it."""
    files = {"main.xml": b'<scene version="3.0.0"><include filename="sub/a.xml"/></scene>',
             "sub/a.xml": b'<scene version="3.0.0"><include filename="b.xml"/>'
                          b'<include filename="c.xml"/></scene>',
             "sub/b.xml": b'<scene version="3.0.0"><spectrum name="s" filename="s.spd"/></scene>',
             "c.xml": b'<scene version="3.0.0"/>', "s.spd": SPECTRUM, "sub/s.spd": SPECTRUM}
    found = bundle.closure("main.xml", files.get)
    assert [r.path for r in found["sub/a.xml"]] == ["sub/b.xml", "c.xml"]
    assert [r.path for r in found["sub/b.xml"]] == ["sub/s.spd"]
