#!/usr/bin/env bash
# Build tf2_msgs/msg/TFMessage into .venv/ from its .msg definition, with the rosidl generators
# that come as PyPI wheels (ros-jazzy-rosidl-generator-c/-py, rosidl-typesupport-c,
# -introspection-c, -fastrtps-c; pinned by the message wheels in requirements.txt) and gcc,
# against the headers and libraries of those wheels: tf2_msgs is not on PyPI as a wheel.
#
# What it installs (the layout of the message wheels): .venv/lib/libtf2_msgs__*.so,
# .venv/include/tf2_msgs/, .venv/share/tf2_msgs/ with its ament index entries, and the Python
# package tf2_msgs in site-packages. Only the message TFMessage (what /tf and /tf_static carry)
# is built, not tf2_msgs' services and action (they need action_msgs plumbing ga_ros does not
# use). Idempotent: a stamp records the hash of this script and the .msg file.
# Needs: gcc, g++ (build-essential) and catkin-pkg (requirements.txt).
set -euo pipefail
cd "$(dirname "$0")/.."
V=$(cd "${VENV:-.venv}" && pwd)
PY="$V/bin/python"
stamp="$V/.tf2_msgs_built"
want=$(cat scripts/build_tf2_msgs.sh scripts/tf2_msgs/msg/TFMessage.msg | sha256sum \
  | cut -d' ' -f1)
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] \
    && "$PY" -c 'import tf2_msgs.msg' 2>/dev/null; then
  exit 0
fi
for tool in gcc g++; do
  command -v "$tool" >/dev/null || { echo "[ga_ros] $tool is needed to build tf2_msgs" \
    "(apt-get install build-essential)" >&2; exit 1; }
done
echo "[ga_ros] building tf2_msgs/msg/TFMessage into $V" >&2
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
mkdir -p "$work/src/msg"
cp scripts/tf2_msgs/msg/TFMessage.msg "$work/src/msg/"

# 1. Generate the sources: msg -> idl -> C, typesupports and Python. The generators are called
# directly: `rosidl generate` refuses to run because the wheels register its entry points twice.
AMENT_PREFIX_PATH="$V" "$PY" - "$work" "$V/share" > "$work/generate.log" 2>&1 <<'PYEOF' \
  || { grep -v 'duplicate entry point' "$work/generate.log" >&2; exit 1; }
import pathlib
import sys

from rosidl_adapter.cli import TranslateMsgToIDL
from rosidl_generator_c.cli import GenerateC
from rosidl_generator_py.cli import GeneratePython
from rosidl_typesupport_c.cli import GenerateCTypesupport
from rosidl_typesupport_fastrtps_c.cli import GenerateFastRTPSCTypesupport
from rosidl_typesupport_introspection_c.cli import GenerateIntrospectionCTypesupport

work, share = pathlib.Path(sys.argv[1]), sys.argv[2]
files = TranslateMsgToIDL('msg2idl').translate(
    'tf2_msgs', [f'{work}/src:msg/TFMessage.msg'], [share], work / 'idl')
for name, cls in (('c', GenerateC), ('ts_c', GenerateCTypesupport),
                  ('introspection_c', GenerateIntrospectionCTypesupport),
                  ('fastrtps_c', GenerateFastRTPSCTypesupport), ('py', GeneratePython)):
    cls(name).generate('tf2_msgs', files, [share], work / 'gen' / name / 'tf2_msgs')
PYEOF
G="$work/gen"
[ -f "$G/c/tf2_msgs/msg/tf_message.h" ] \
  || { echo "[ga_ros] tf2_msgs generation failed" >&2; cat "$work/generate.log" >&2; exit 1; }

# 2. Compile (as rosidl_generate_interfaces would) and install.
site=$("$PY" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
pyinc=$("$PY" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
npinc=$("$PY" -c 'import numpy; print(numpy.get_include())')
inc=(-I"$G/c" -I"$G/introspection_c" -I"$G/fastrtps_c" -I"$G/ts_c")
inc+=(-I"$V/include")
for d in "$V"/include/*/; do inc+=(-I"$d"); done
L="$V/lib"
cc() { gcc -O2 -fPIC -shared -std=c11 "${inc[@]}" "$@" -L"$L" -Wl,-rpath,"$L"; }
cxx() { g++ -O2 -fPIC -shared -std=c++17 "${inc[@]}" "$@" -L"$L" -Wl,-rpath,"$L"; }
D="$G/c/tf2_msgs/msg/detail"
cc -o "$L/libtf2_msgs__rosidl_generator_c.so" "$D/tf_message__functions.c" \
  "$D/tf_message__description.c" -lgeometry_msgs__rosidl_generator_c \
  -lstd_msgs__rosidl_generator_c -lbuiltin_interfaces__rosidl_generator_c -lrosidl_runtime_c \
  -lrcutils
cc -o "$L/libtf2_msgs__rosidl_typesupport_introspection_c.so" \
  "$G/introspection_c/tf2_msgs/msg/detail/tf_message__type_support.c" \
  -ltf2_msgs__rosidl_generator_c -lgeometry_msgs__rosidl_typesupport_introspection_c \
  -lrosidl_runtime_c
cxx -o "$L/libtf2_msgs__rosidl_typesupport_fastrtps_c.so" \
  "$G/fastrtps_c/tf2_msgs/msg/detail/tf_message__type_support_c.cpp" \
  -ltf2_msgs__rosidl_generator_c -lgeometry_msgs__rosidl_typesupport_fastrtps_c \
  -lgeometry_msgs__rosidl_generator_c -lrosidl_typesupport_fastrtps_c \
  -lrosidl_typesupport_fastrtps_cpp -lrosidl_runtime_c -lfastcdr -lrmw -lrcutils
cxx -o "$L/libtf2_msgs__rosidl_typesupport_c.so" \
  "$G/ts_c/tf2_msgs/msg/tf_message__type_support.cpp" \
  -ltf2_msgs__rosidl_generator_c -lrosidl_typesupport_c -lrosidl_runtime_c -lrcpputils -lrcutils
cc -I"$pyinc" -I"$npinc" -o "$L/libtf2_msgs__rosidl_generator_py.so" \
  "$G/py/tf2_msgs/msg/_tf_message_s.c" -ltf2_msgs__rosidl_generator_c \
  -ltf2_msgs__rosidl_typesupport_c -lgeometry_msgs__rosidl_generator_py \
  -lgeometry_msgs__rosidl_generator_c -lrosidl_runtime_c -lrcutils
pkg="$site/tf2_msgs"
rm -rf "$pkg"
mkdir -p "$pkg/msg"
cp "$G/py/tf2_msgs/msg/__init__.py" "$G/py/tf2_msgs/msg/_tf_message.py" "$pkg/msg/"
: > "$pkg/__init__.py"
for ts in rosidl_typesupport_c rosidl_typesupport_fastrtps_c rosidl_typesupport_introspection_c
do
  cc -I"$pyinc" -I"$npinc" -o "$pkg/tf2_msgs_s__$ts.so" "$G/py/tf2_msgs/_tf2_msgs_s.ep.$ts.c" \
    -ltf2_msgs__rosidl_generator_py -ltf2_msgs__$ts -ltf2_msgs__rosidl_generator_c \
    -lrosidl_runtime_c -lrcutils
done
rm -rf "$V/include/tf2_msgs" "$V/share/tf2_msgs"
mkdir -p "$V/include/tf2_msgs" "$V/share/tf2_msgs/msg"
for g in c introspection_c fastrtps_c; do
  (cd "$G/$g" && find tf2_msgs -name '*.h' -exec cp --parents {} "$V/include/tf2_msgs/" \;)
done
cp scripts/tf2_msgs/msg/TFMessage.msg "$work/idl/msg/TFMessage.idl" \
  "$G/c/tf2_msgs/msg/TFMessage.json" "$V/share/tf2_msgs/msg/"
idx="$V/share/ament_index/resource_index"
mkdir -p "$idx/packages" "$idx/rosidl_interfaces"
: > "$idx/packages/tf2_msgs"
printf 'msg/TFMessage.idl\nmsg/TFMessage.msg\n' > "$idx/rosidl_interfaces/tf2_msgs"
"$PY" -c 'from tf2_msgs.msg import TFMessage; TFMessage()' \
  || { echo "[ga_ros] tf2_msgs was built but does not import" >&2; exit 1; }
echo "$want" > "$stamp"
