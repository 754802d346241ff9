"""Motion capture into the pose columns: Motive's CSV export and the plain layout,
written here from a known path, import exactly; a recording is filled on its own times."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mecanum_hil.cli import main
from mecanum_hil.importers import detect_format, import_source
from mecanum_hil.io.recording import empty_like_times, read_recording, write_recording
from mecanum_hil.model import load_calibration, load_robot_profile
from mecanum_hil.prediction import predict


def path_truth():
    """The model driving diagonally while turning from rest (pose at 100 Hz)."""
    t = np.arange(0.0, 4.0 + 1e-9, 0.01)
    cmd = np.zeros((t.size, 3))
    cmd[:, 2] = 60.0
    on = (t >= 0.5) & (t < 3.0)
    cmd[on, 0], cmd[on, 1] = 60.0, 30.0
    return predict(empty_like_times(t).with_values(commands=cmd), load_calibration(),
                   load_robot_profile())


def quat_z(yaw_rad):
    """Quaternions (x, y, z, w) of turns about z."""
    return np.column_stack([np.zeros_like(yaw_rad), np.zeros_like(yaw_rad),
                            np.sin(yaw_rad / 2), np.cos(yaw_rad / 2)])


def write_motive(path, t, pose, occluded=(), q=None, unit=("Millimeters", 1000.0)):
    """Motive's export of rigid body 'robot' (Y up, millimetres) plus a second body and a
    marker to be ignored; the body's own x axis is the robot's forward axis (unless its
    quaternions ``q`` are given); ``pose`` is the body's pivot on the floor."""
    yaw = np.radians(pose[:, 2])
    # floor (X, Y, Z up) -> Motive (X, Y up, Z = -floor Y); a turn about floor z is one about
    # Motive's y by the same angle
    if q is None:
        q = np.column_stack([np.zeros_like(yaw), np.sin(yaw / 2), np.zeros_like(yaw),
                             np.cos(yaw / 2)])
    px, py, pz = (pose[:, 0] * unit[1], np.full(len(t), 0.23 * unit[1]),
                  -pose[:, 1] * unit[1])
    head = ("Format Version,1.23,Take Name,Take 2026-11-23,Take Notes,,Capture Frame Rate,"
            "100.000000,Export Frame Rate,100.000000,Capture Start Time,2026-11-23 05.00.00.000"
            " AM,Total Frames in Take,{n},Total Exported Frames,{n},Rotation Type,Quaternion,"
            "Length Units,{unit},Coordinate Space,Global").format(n=len(t), unit=unit[0])
    rb = ["Rigid Body"] * 8
    lines = [head, "",
             ",Type," + ",".join(rb + ["Rigid Body"] * 7 + ["Marker"] * 3),
             ",Name," + ",".join(["robot"] * 8 + ["cart"] * 7 + ["robot:Marker1"] * 3),
             ",ID," + ",".join(["1"] * 8 + ["2"] * 7 + ["3"] * 3),
             ",," + ",".join(["Rotation"] * 4 + ["Position"] * 3 + ["Mean Marker Error"]
                             + ["Rotation"] * 4 + ["Position"] * 3 + ["Position"] * 3),
             "Frame,Time (Seconds)," + ",".join(list("XYZW") + list("XYZ") + [""]
                                                + list("XYZW") + list("XYZ") + list("XYZ"))]
    for i in range(len(t)):
        if i in occluded:
            body = [""] * 8
        else:
            body = [f"{v:.9f}" for v in (*q[i], px[i], py[i], pz[i])] + ["0.000213"]
        other = ["0", "0", "0", "1", "500.0", "0.0", "200.0"]
        marker = ["1.0", "2.0", "3.0"]
        lines.append(f"{i},{t[i]:.6f}," + ",".join(body + other + marker))
    path.write_text("\r\n".join(lines) + "\r\n")


def test_motive_export_imports_exactly(tmp_path, capsys):
    truth = path_truth()
    t = np.arange(0.0, 3.5, 0.01)
    pose = np.column_stack([np.interp(t, truth.t_s, truth.pose[:, k]) for k in range(3)])
    src = tmp_path / "take.csv"
    write_motive(src, t, pose, occluded={40, 41, 42})
    assert detect_format(src) == "mocap"
    with pytest.raises(Exception, match="several rigid bodies"):
        import_source(src)
    mp = tmp_path / "map.toml"
    mp.write_text('[mocap]\nrigid_body = "robot"\n')
    res = import_source(src, map_path=mp)
    rec = res.recording
    ok = np.isfinite(rec.pose).all(axis=1)
    assert (~ok).sum() == 3 and not ok[40:43].any()
    np.testing.assert_allclose(rec.t_s, t, atol=1e-9)
    np.testing.assert_allclose(rec.pose[ok, :2], pose[ok, :2], atol=1e-8)
    np.testing.assert_allclose(rec.pose[ok, 2], pose[ok, 2], atol=1e-6)
    assert any("occluded" in n for n in res.notes)
    assert rec.metadata["rigid_body"] == "robot"
    # through the command, into a recording's own times, the start given
    base = tmp_path / "rec.csv"
    write_recording(truth.with_values(pose=np.full_like(truth.pose, np.nan)), base)
    out = tmp_path / "with_pose.csv"
    assert main(["import", str(src), "--map", str(mp), "--recording", str(base), "--start-s", "0.2",
                 "--out", str(out)]) == 0
    got = read_recording(out)
    np.testing.assert_allclose(got.commands, truth.commands)
    inside = (got.t_s >= 0.2) & (got.t_s <= 0.2 + t[-1])
    gap = (got.t_s > 0.2 + t[39]) & (got.t_s < 0.2 + t[43])
    have = np.isfinite(got.pose).all(axis=1)
    assert not have[~inside].any() and not have[gap].any()  # no extrapolation, no bridging
    assert have[inside & ~gap].all()
    expect = np.column_stack([np.interp(got.t_s[have] - 0.2, t, pose[:, k]) for k in range(3)])
    np.testing.assert_allclose(got.pose[have], expect, atol=1e-6)
    assert got.metadata["pose_import"]["capture_start_s"] == 0.2


def test_plain_csv_with_a_transform_and_auto_start(tmp_path):
    truth = path_truth()
    t = np.arange(0.0, 3.6, 1 / 120)
    pose = np.column_stack([np.interp(t, truth.t_s + 0.3, truth.pose[:, k]) for k in range(3)])
    # the capture frame: z up, turned 30 deg from the floor's and shifted; units mm; the body's
    # forward axis is its y axis, and the robot's centre 0.1 m behind the body's pivot
    a = math.radians(30.0)
    rot = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    shift = np.array([1.5, -0.4, 0.0])
    phi = np.radians(pose[:, 2])
    centre = np.column_stack([pose[:, :2], np.full(len(t), 0.23)])
    pivot = centre + 0.1 * np.column_stack([np.cos(phi), np.sin(phi), np.zeros(len(t))])
    cap = (pivot - shift) @ rot  # rot.T @ (floor - shift): floor = rot @ capture + shift
    body_yaw = phi - a - math.pi / 2  # its y axis along the robot's forward axis
    q = quat_z(body_yaw)
    src = tmp_path / "mocap.csv"
    rows = ["t, x, y, z, qx, qy, qz, qw"]
    for i in range(len(t)):
        rows.append(",".join(f"{v:.10g}" for v in (t[i] + 12.0, *(cap[i] * 1000), *q[i])))
    src.write_text("\n".join(rows) + "\n")
    mp = tmp_path / "map.toml"
    mp.write_text(f"""[mocap]
units = "mm"
rotation = [[{float(rot[0, 0])!r}, {float(rot[0, 1])!r}, 0.0],
            [{float(rot[1, 0])!r}, {float(rot[1, 1])!r}, 0.0], [0.0, 0.0, 1.0]]
translation_m = [1.5, -0.4, 0.0]
forward_axis = [0.0, 1.0, 0.0]
centre_m = [0.0, -0.1, 0.0]   # in the body's frame: 0.1 m behind, along its y axis
""")
    assert detect_format(src) == "mocap"
    rec = import_source(src, map_path=mp).recording
    np.testing.assert_allclose(rec.t_s, t, atol=1e-7)  # from the first sample
    np.testing.assert_allclose(rec.pose[:, :2], pose[:, :2], atol=1e-7)
    np.testing.assert_allclose(rec.pose[:, 2], pose[:, 2], atol=1e-6)
    # auto start: the capture began 0.3 s before the recording; found from the motion onset
    base = tmp_path / "rec.csv"
    write_recording(truth.with_values(pose=np.full_like(truth.pose, np.nan)), base)
    out = tmp_path / "with_pose.csv"
    assert main(["import", str(src), "--map", str(mp), "--recording", str(base),
                 "--out", str(out)]) == 0  # auto is the default with --recording
    got = read_recording(out)
    assert got.metadata["pose_import"]["capture_start_s"] == pytest.approx(-0.3, abs=0.01)
    assert got.metadata["pose_import"]["capture_start_method"].startswith("auto")
    have = np.isfinite(got.pose).all(axis=1)
    err = np.hypot(*(got.pose[have, :2] - truth.pose[have, :2]).T)
    assert err.max() < 0.01
    # the library alone has no model (it is a layer above): auto then asks for it
    with pytest.raises(Exception, match="model's prediction"):
        import_source(src, map_path=mp, recording=base, start_s="auto")


def test_bad_mocap_input(tmp_path, capsys):
    src = tmp_path / "m.csv"
    src.write_text("t, x, y, z, qx, qy, qz, qw\n0, 0, 0, 0, 0, 0, 0, 1\n0.1, 0, zero, 0, 0, 0, "
                   "0, 1\n")
    assert main(["import", str(src), "--out", str(tmp_path / "o.csv")]) == 1
    err = capsys.readouterr().err
    assert "line 3" in err and "'y'" in err
    mp = tmp_path / "map.toml"
    mp.write_text("[mocap]\nrotation = [[1, 0, 0], [0, 1, 0], [0, 0, -1]]\n")
    src.write_text("t, x, y, z, qx, qy, qz, qw\n0, 0, 0, 0, 0, 0, 0, 1\n0.1, 0, 0, 0, 0, 0, 0, 1\n")
    assert main(["import", str(src), "--map", str(mp), "--out", str(tmp_path / "o.csv")]) == 1
    assert "determinant" in capsys.readouterr().err
    assert main(["import", str(src), "--start-s", "auto", "--out", str(tmp_path / "o.csv")]) == 1
    assert "needs --recording" in capsys.readouterr().err
    for text in ("\n\n", "# only a comment\n", ",,,\n"):  # no header at all: one line too
        src.write_text(text)
        assert main(["import", str(src), "--format", "mocap", "--out",
                     str(tmp_path / "o.csv")]) == 1
        assert "expected the header t, x, y, z" in capsys.readouterr().err
    motive = tmp_path / "take.csv"
    write_motive(motive, np.arange(3) * 0.01, np.zeros((3, 3)))
    motive.write_text(motive.read_text().replace("Quaternion", "XYZ"))
    mp.write_text('[mocap]\nrigid_body = "robot"\n')
    args = ["import", str(motive), "--map", str(mp), "--out", str(tmp_path / "o.csv")]
    assert main(args) == 1
    assert "Rotation Type = Quaternion" in capsys.readouterr().err


def test_motive_body_axes_other_than_the_robots(tmp_path):
    """A rigid body whose own frame is Y up with the robot's front along its -Z axis (as Motive
    makes a body from markers placed that way), the robot on a 4 deg side slope, centimetres,
    the capture's origin 1 m / 2 m off the floor's: heading and place as worked out by hand."""
    n = 40
    t = np.arange(n) / 120.0
    phi = np.radians(np.linspace(-170.0, 200.0, n))  # through +-180: heading continuous
    # body -> Motive: first Ry(-90 deg) (body -Z onto Motive +X, the robot's front at phi = 0),
    # then a 4 deg roll about the front axis (Motive X), then the heading about Motive Y
    def qy(a):
        return np.array([0.0, math.sin(a / 2), 0.0, math.cos(a / 2)])

    def mul(a, b):  # Hamilton product of (x, y, z, w) quaternions
        ax, ay, az, aw = a
        bx, by, bz, bw = b
        return np.array([aw * bx + ax * bw + ay * bz - az * by,
                         aw * by - ax * bz + ay * bw + az * bx,
                         aw * bz + ax * by - ay * bx + az * bw,
                         aw * bw - ax * bx - ay * by - az * bz])

    roll = math.radians(4.0)
    qx = np.array([math.sin(roll / 2), 0.0, 0.0, math.cos(roll / 2)])
    q = np.array([mul(qy(a), mul(qx, qy(-math.pi / 2))) for a in phi])
    # the pivot on the floor, in the capture's frame (floor = capture + (1, 2, 0))
    floor_xy = np.column_stack([0.5 * np.cos(phi), 0.5 * np.sin(phi)])
    capture_xy = floor_xy - [1.0, 2.0]
    src = tmp_path / "take.csv"
    write_motive(src, t, np.column_stack([capture_xy, np.zeros(n)]), q=q,
                 unit=("Centimeters", 100.0))
    mp = tmp_path / "map.toml"
    mp.write_text('[mocap]\nrigid_body = "robot"\nup = "y"\ntranslation_m = [1.0, 2.0, 0.0]\n'
                  "forward_axis = [0.0, 0.0, -1.0]\n")
    rec = import_source(src, map_path=mp).recording
    np.testing.assert_allclose(rec.pose[:, :2], floor_xy, atol=1e-7)
    np.testing.assert_allclose(rec.pose[:, 2], np.degrees(phi), atol=1e-5)
    assert rec.metadata["capture_to_floor"]["scale_m_per_unit"] == 0.01


# -- cut exports, missing unit, degenerate axis, no overlap ---------------------------------

def _take(tmp_path, unit=("Millimeters", 1000.0)):
    truth = path_truth()
    t = np.arange(0.0, 3.5, 0.01)
    pose = np.column_stack([np.interp(t, truth.t_s, truth.pose[:, k]) for k in range(3)])
    src = tmp_path / "take.csv"
    write_motive(src, t, pose, unit=unit)
    mp = tmp_path / "map.toml"
    mp.write_text('[mocap]\nrigid_body = "robot"\n')
    return src, mp, t


def test_a_cut_last_line_is_dropped_and_a_short_line_named(tmp_path, one_line_error):
    src, mp, t = _take(tmp_path)
    text = src.read_text()
    src.write_text(text[: len(text) - 40])  # cut mid-number: fewer fields than the header
    res = import_source(src, map_path=mp)
    assert len(res.recording) == t.size - 1
    assert any("last line cut off mid-row" in n and "dropped" in n for n in res.notes)
    lines = text.splitlines(True)
    lines[50] = ",".join(lines[50].split(",")[:9]) + "\r\n"
    src.write_text("".join(lines))
    err = one_line_error(["import", str(src), "--map", str(mp), "--out",
                          str(tmp_path / "r.csv")])
    assert "line 51: 9 fields, fewer than the header's 20" in err


def test_a_motive_export_without_its_unit_needs_the_maps(tmp_path, one_line_error):
    src, mp, _ = _take(tmp_path)
    src.write_text(src.read_text().replace("Length Units,Millimeters,", ""))
    err = one_line_error(["import", str(src), "--map", str(mp), "--out",
                          str(tmp_path / "r.csv")])
    assert "does not state its length unit" in err and "units" in err
    mp.write_text('[mocap]\nrigid_body = "robot"\nunits = "mm"\n')
    ref = import_source(src, map_path=mp)
    assert np.nanmax(np.abs(ref.recording.pose[:, :2])) < 10.0  # metres, not millimetres


def test_a_vertical_forward_axis_is_refused(tmp_path):
    from mecanum_hil.errors import ConfigError

    src, mp, _ = _take(tmp_path)
    mp.write_text('[mocap]\nrigid_body = "robot"\nforward_axis = [0.0, 1.0, 0.0]\n')  # Motive up
    with pytest.raises(ConfigError, match=r"mocap\.forward_axis.*does not project onto the floor"):
        import_source(src, map_path=mp)


def test_a_start_without_overlap_is_refused(tmp_path, one_line_error):
    src, mp, _ = _take(tmp_path)
    rec = tmp_path / "rec.csv"
    write_recording(empty_like_times(np.arange(0.0, 3.0, 0.01)), rec)
    err = one_line_error(["import", str(src), "--map", str(mp), "--recording", str(rec),
                          "--start-s", "50", "--out", str(tmp_path / "r.csv")])
    assert "does not overlap the recording" in err and "50.000 to 53.490 s" in err
