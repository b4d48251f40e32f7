# Cross-compiling the agent for 64-bit ARM boards (Debian 12 arm64: Raspberry Pi 4/5, Jetson, i.MX8, RK3588).
#
# The libraries come from a Debian arm64 sysroot that toolchains/make_sysroot.sh builds and caches; the
# compilers (g++-aarch64-linux-gnu) and the code generators (protoc, grpc_cpp_plugin) are the host's. Tests
# and tools run under qemu-aarch64 (user mode), so CTest works as on the host. Use the board-aarch64 preset:
#
#   toolchains/make_sysroot.sh && cmake --preset board-aarch64 && cmake --build --preset board-aarch64
#
# The sysroot is taken from CVISLAM_SYSROOT (cache or environment), else out/sysroot/arm64-bookworm.
set(CMAKE_SYSTEM_NAME Linux)
set(CMAKE_SYSTEM_PROCESSOR aarch64)
set(CMAKE_C_COMPILER aarch64-linux-gnu-gcc)
set(CMAKE_CXX_COMPILER aarch64-linux-gnu-g++)
set(CMAKE_LIBRARY_ARCHITECTURE aarch64-linux-gnu)

if(NOT CVISLAM_SYSROOT)
  if(DEFINED ENV{CVISLAM_SYSROOT})
    set(CVISLAM_SYSROOT "$ENV{CVISLAM_SYSROOT}")
  else()
    get_filename_component(CVISLAM_SYSROOT "${CMAKE_CURRENT_LIST_DIR}/../out/sysroot/arm64-bookworm" ABSOLUTE)
  endif()
endif()
set(CVISLAM_SYSROOT "${CVISLAM_SYSROOT}" CACHE PATH "Debian arm64 sysroot (toolchains/make_sysroot.sh)")
if(NOT EXISTS "${CVISLAM_SYSROOT}/.cvislam-sysroot")
  message(FATAL_ERROR "No arm64 sysroot at ${CVISLAM_SYSROOT}: run toolchains/make_sysroot.sh first "
                      "(or point CVISLAM_SYSROOT at one it made)")
endif()
set(CMAKE_SYSROOT "${CVISLAM_SYSROOT}")
set(CMAKE_FIND_ROOT_PATH "${CVISLAM_SYSROOT}")
set(CMAKE_FIND_ROOT_PATH_MODE_PROGRAM NEVER)   # protoc and grpc_cpp_plugin run on the host
set(CMAKE_FIND_ROOT_PATH_MODE_LIBRARY ONLY)
set(CMAKE_FIND_ROOT_PATH_MODE_INCLUDE ONLY)
set(CMAKE_FIND_ROOT_PATH_MODE_PACKAGE ONLY)

# -L: the sysroot has its own libc and loader. (With a multiarch host install, -L /usr/aarch64-linux-gnu makes
# gRPC and OpenCV tests hang; with a complete sysroot it is right.)
set(CMAKE_CROSSCOMPILING_EMULATOR qemu-aarch64 -L "${CVISLAM_SYSROOT}")
