#!/usr/bin/env bash
# Build a ROS 2 interface package (its msg/*.msg and srv/*.srv) into .venv/, with the rosidl
# generators that come as PyPI wheels and gcc, against the headers and libraries of the message
# wheels: for interface packages that are not on PyPI as wheels.
#
#   bash scripts/build_interfaces.sh PACKAGE SOURCE_DIR [DEPENDENCY ...]
#
# SOURCE_DIR holds msg/ and/or srv/; each DEPENDENCY is an interface package already in .venv/
# whose types the definitions use (services also need service_msgs and builtin_interfaces, for
# their Event message). Installs the layout of the message wheels: .venv/lib/libPACKAGE__*.so,
# .venv/include/PACKAGE/, .venv/share/PACKAGE/ with its ament index entries, and the Python
# package PACKAGE in site-packages. Idempotent: a stamp .venv/.PACKAGE_built records the hash of
# this script and the definitions. Needs gcc, g++ (build-essential) and catkin-pkg
# (requirements.txt). Used for tf2_msgs (scripts/build_tf2_msgs.sh) and, by scripts/venv.sh when
# the shared vendor folder is there, composition_interfaces (launch_ros imports its services;
# tests only).
set -euo pipefail
[ $# -ge 2 ] || { echo "usage: $0 PACKAGE SOURCE_DIR [DEPENDENCY ...]" >&2; exit 2; }
pkg_name=$1
src=$(cd "$2" && pwd)
shift 2
deps=("$@")
cd "$(dirname "$0")/.."
V=$(cd "${VENV:-.venv}" && pwd -P)
PY="$V/bin/python"
defs=$(cd "$src" && for kind in msg srv; do
  [ ! -d "$kind" ] || find "$kind" -maxdepth 1 -name "*.$kind"; done | sort)
[ -n "$defs" ] || { echo "[ga_ros] no msg/*.msg or srv/*.srv in $src" >&2; exit 1; }
stamp="$V/.${pkg_name}_built"
want=$( (cat scripts/build_interfaces.sh; echo "${deps[*]}"; cd "$src" && cat $defs) \
  | sha256sum | cut -d' ' -f1)
# the first definition, imported and instantiated (loads the type support)
probe=$(echo "$defs" | head -1 | sed -E -e 's#^msg/([^.]*)\..*#from '"$pkg_name"'.msg import \1; \1()#' \
  -e 's#^srv/([^.]*)\..*#from '"$pkg_name"'.srv import \1; \1.Request(); \1.Response()#')
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] && "$PY" -c "$probe" 2>/dev/null; then
  exit 0
fi
for tool in gcc g++; do
  command -v "$tool" >/dev/null || { echo "[ga_ros] $tool is needed to build $pkg_name" \
    "(apt-get install build-essential)" >&2; exit 1; }
done
echo "[ga_ros] building $pkg_name ($(echo $defs | tr '\n' ' ')) into $V" >&2
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
mkdir -p "$work/src"
for d in $defs; do   # writable copies (the source folder may be read-only)
  mkdir -p "$work/src/$(dirname "$d")"
  cp --no-preserve=mode "$src/$d" "$work/src/$d"
done

# 1. Generate the sources: msg/srv -> idl -> C, typesupports and Python. The generators are
# called directly: `rosidl generate` refuses to run because the wheels register its entry points
# twice.
AMENT_PREFIX_PATH="$V" "$PY" - "$pkg_name" "$work" "$V/share" $defs > "$work/generate.log" 2>&1 \
  <<'PYEOF' || { grep -v 'duplicate entry point' "$work/generate.log" >&2; exit 1; }
import pathlib
import sys

from rosidl_adapter.cli import TranslateMsgToIDL, TranslateSrvToIDL
from rosidl_generator_c.cli import GenerateC
from rosidl_generator_py.cli import GeneratePython
from rosidl_typesupport_c.cli import GenerateCTypesupport
from rosidl_typesupport_fastrtps_c.cli import GenerateFastRTPSCTypesupport
from rosidl_typesupport_introspection_c.cli import GenerateIntrospectionCTypesupport

package, work, share, defs = sys.argv[1], pathlib.Path(sys.argv[2]), sys.argv[3], sys.argv[4:]
files = []
for suffix, cls in (('.msg', TranslateMsgToIDL), ('.srv', TranslateSrvToIDL)):
    mine = [f'{work}/src:{d}' for d in defs if d.endswith(suffix)]
    if mine:
        files += cls(suffix[1:] + '2idl').translate(package, mine, [share], work / 'idl')
for name, cls in (('c', GenerateC), ('ts_c', GenerateCTypesupport),
                  ('introspection_c', GenerateIntrospectionCTypesupport),
                  ('fastrtps_c', GenerateFastRTPSCTypesupport), ('py', GeneratePython)):
    cls(name).generate(package, files, [share], work / 'gen' / name / package)
PYEOF
G="$work/gen"
[ -d "$G/py/$pkg_name" ] \
  || { echo "[ga_ros] $pkg_name generation failed" >&2; cat "$work/generate.log" >&2; exit 1; }

# 2. Compile (as rosidl_generate_interfaces would: one library per generator and typesupport,
# linked against the same libraries of the dependencies) and install.
site=$("$PY" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
pyinc=$("$PY" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
npinc=$("$PY" -c 'import numpy; print(numpy.get_include())')
inc=(-I"$G/c" -I"$G/introspection_c" -I"$G/fastrtps_c" -I"$G/ts_c" -I"$V/include")
for d in "$V"/include/*/; do inc+=(-I"$d"); done
L="$V/lib"
P=$pkg_name
cc() { gcc -O2 -fPIC -shared -std=c11 "${inc[@]}" "$@" -L"$L" -Wl,-rpath,"$L"; }
cxx() { g++ -O2 -fPIC -shared -std=c++17 "${inc[@]}" "$@" -L"$L" -Wl,-rpath,"$L"; }
# the dependencies' libraries of one kind: -ldep__KIND ...
dep_libs() { for d in "${deps[@]}"; do printf -- '-l%s__%s ' "$d" "$1"; done; }
sources() { find "$1" -name "$2" | sort; }
# shellcheck disable=SC2046
cc -o "$L/lib${P}__rosidl_generator_c.so" $(sources "$G/c" '*.c') \
  $(dep_libs rosidl_generator_c) -lrosidl_runtime_c -lrcutils
# shellcheck disable=SC2046
cc -o "$L/lib${P}__rosidl_typesupport_introspection_c.so" $(sources "$G/introspection_c" '*.c') \
  -l"${P}__rosidl_generator_c" $(dep_libs rosidl_typesupport_introspection_c) \
  $(dep_libs rosidl_generator_c) -lrosidl_runtime_c -lrcutils
# shellcheck disable=SC2046
cxx -o "$L/lib${P}__rosidl_typesupport_fastrtps_c.so" $(sources "$G/fastrtps_c" '*.cpp') \
  -l"${P}__rosidl_generator_c" $(dep_libs rosidl_typesupport_fastrtps_c) \
  $(dep_libs rosidl_generator_c) -lrosidl_typesupport_fastrtps_c \
  -lrosidl_typesupport_fastrtps_cpp -lrosidl_runtime_c -lfastcdr -lrmw -lrcutils
# shellcheck disable=SC2046
cxx -o "$L/lib${P}__rosidl_typesupport_c.so" $(sources "$G/ts_c" '*.cpp') \
  -l"${P}__rosidl_generator_c" -lrosidl_typesupport_c -lrosidl_runtime_c -lrcpputils -lrcutils
# shellcheck disable=SC2046
cc -I"$pyinc" -I"$npinc" -o "$L/lib${P}__rosidl_generator_py.so" \
  $(sources "$G/py" '*_s.c' | grep -v '\.ep\.') -l"${P}__rosidl_generator_c" \
  -l"${P}__rosidl_typesupport_c" $(dep_libs rosidl_generator_py) \
  $(dep_libs rosidl_generator_c) -lrosidl_runtime_c -lrcutils
pkg="$site/$P"
rm -rf "$pkg"
mkdir -p "$pkg"
(cd "$G/py/$P" && find . -name '*.py' -exec cp --parents {} "$pkg/" \;)
: > "$pkg/__init__.py"
for ts in rosidl_typesupport_c rosidl_typesupport_fastrtps_c rosidl_typesupport_introspection_c
do
  cc -I"$pyinc" -I"$npinc" -o "$pkg/${P}_s__$ts.so" "$G/py/$P/_${P}_s.ep.$ts.c" \
    -l"${P}__rosidl_generator_py" -l"${P}__$ts" -l"${P}__rosidl_generator_c" \
    -lrosidl_runtime_c -lrcutils
done
rm -rf "$V/include/$P" "$V/share/$P"
mkdir -p "$V/include/$P" "$V/share/$P"
for g in c introspection_c fastrtps_c; do
  (cd "$G/$g" && find "$P" -name '*.h' -exec cp --parents {} "$V/include/$P/" \;)
done
index=()
for d in $defs; do
  dir=$(dirname "$d") name=$(basename "$d")
  mkdir -p "$V/share/$P/$dir"
  cp --no-preserve=mode "$src/$d" "$work/idl/$dir/${name%.*}.idl" "$G/c/$P/$dir/${name%.*}.json" "$V/share/$P/$dir/"
  index+=("$dir/${name%.*}.idl" "$d")
done
idx="$V/share/ament_index/resource_index"
mkdir -p "$idx/packages" "$idx/rosidl_interfaces"
: > "$idx/packages/$P"
printf '%s\n' "${index[@]}" > "$idx/rosidl_interfaces/$P"
"$PY" -c "$probe" || { echo "[ga_ros] $P was built but does not import" >&2; exit 1; }
echo "$want" > "$stamp"
