"""Makes the robot models of tests/test_robots.py from a MuJoCo Menagerie checkout: each robot's
scene and model files with every mesh, height field and image file left out (the geoms that
drew or collided with a mesh go with them), so that the models are a few kilobytes, load with
no asset, and keep the robot's bodies, joints, actuators, sensors, options and primitive
collision geoms. Run by hand; the tests read what it wrote (with each robot's LICENSE).

    python tests/robots/make_robots.py PATH/TO/mujoco_menagerie
"""

from __future__ import annotations

import pathlib
import shutil
import sys
import xml.etree.ElementTree as ET

import mujoco

# robot folder -> its scene file
ROBOTS = {
    "unitree_go1": "scene.xml", "unitree_go2": "scene.xml", "anybotics_anymal_c": "scene.xml",
    "unitree_h1": "scene.xml", "booster_t1": "scene.xml", "unitree_g1": "scene.xml",
    "agility_cassie": "scene.xml", "universal_robots_ur5e": "scene.xml",
    "franka_emika_panda": "scene.xml", "ufactory_xarm7": "scene.xml",
    "skydio_x2": "scene.xml", "bitcraze_crazyflie_2": "scene.xml",
}
HERE = pathlib.Path(__file__).parent


def mesh_classes(root: ET.Element) -> set[str]:
    """The default classes whose geoms are meshes (and the classes inside them)."""
    out: set[str] = set()

    def walk(node: ET.Element, inherited: bool) -> None:
        for d in node.findall("default"):
            geom = d.find("geom")
            mesh = inherited
            if geom is not None and "type" in geom.attrib:
                mesh = geom.get("type") == "mesh"
            if mesh and "class" in d.attrib:
                out.add(d.get("class"))
            walk(d, mesh)
    for d in root.iter("default"):
        if d.get("class") is None:  # the top default
            walk(d, False)
    return out


def strip(path: pathlib.Path, out: pathlib.Path) -> None:
    tree = ET.parse(path)
    root = tree.getroot()
    meshy = mesh_classes(root)
    for parent in list(root.iter()):
        for child in list(parent):
            file_asset = child.tag in ("mesh", "hfield", "skin") or (
                child.tag == "texture" and "file" in child.attrib)
            mesh_geom = child.tag == "geom" and (
                "mesh" in child.attrib or child.get("type") in ("mesh", "hfield")
                or ("type" not in child.attrib and child.get("class") in meshy))
            if file_asset or mesh_geom:
                parent.remove(child)
    textures = {t.get("name") for t in root.iter("texture")}
    for material in root.iter("material"):
        if material.get("texture") not in (None, *textures):
            del material.attrib["texture"]
    for compiler in root.iter("compiler"):
        compiler.attrib.pop("meshdir", None)
        compiler.attrib.pop("texturedir", None)
    tree.write(out)


def main(menagerie: str) -> None:
    for robot, scene in ROBOTS.items():
        source, target = pathlib.Path(menagerie) / robot, HERE / robot
        target.mkdir(exist_ok=True)
        for xml in source.glob("*.xml"):
            strip(xml, target / xml.name)
        shutil.copy(source / "LICENSE", target / "LICENSE")
        model = mujoco.MjModel.from_xml_path(str(target / scene))
        print(f"{robot}: nbody={model.nbody} ngeom={model.ngeom} nu={model.nu} "
              f"nsensor={model.nsensor}")


if __name__ == "__main__":
    main(sys.argv[1])
