# Every third-party package the build uses, found once. deploy/install_deps.sh installs exactly these
# (Debian 12 package names are given next to each).

find_package(Eigen3 3.4 REQUIRED CONFIG)              # libeigen3-dev
# BLAS: the generic libblas.so.3, which update-alternatives points at OpenBLAS where installed (install_deps.sh
# does) and at ATLAS's otherwise. Debian's Ceres names ATLAS's own libf77blas and libatlas as well, and so does
# CMake's FindBLAS (which SuiteSparse's module calls) unless told the vendor. Loaded first, ATLAS's dgemm_/dsyrk_
# take the place of the selected BLAS for every library of the process, CHOLMOD's supernodal factorisation
# included, which is most of a global BA on a dense map.
set(BLA_VENDOR Generic)
find_package(Ceres 2.1 REQUIRED CONFIG)              # libceres-dev (static libceres.a; pulls glog, gflags, SuiteSparse)
get_target_property(_ceres_link Ceres::ceres INTERFACE_LINK_LIBRARIES)
list(FILTER _ceres_link EXCLUDE REGEX "lib(f77blas|atlas)\\.so$")
set_target_properties(Ceres::ceres PROPERTIES INTERFACE_LINK_LIBRARIES "${_ceres_link}")
unset(_ceres_link)
find_package(iceoryx_hoofs REQUIRED CONFIG)         # libiceoryx-hoofs-dev
find_package(iceoryx_posh REQUIRED CONFIG)          # libiceoryx-posh-dev (+ libacl1-dev for the RouDi headers)
find_package(yaml-cpp REQUIRED CONFIG)                # libyaml-cpp-dev  (target: yaml-cpp, no namespace in 0.7)
find_package(fmt REQUIRED CONFIG)                     # libfmt-dev
find_package(nlohmann_json 3.10 REQUIRED CONFIG)      # nlohmann-json3-dev
find_package(CLI11 REQUIRED CONFIG)                   # libcli11-dev
find_package(Protobuf REQUIRED)                       # libprotobuf-dev protobuf-compiler (CMake's FindProtobuf)
find_package(gRPC REQUIRED CONFIG)                    # libgrpc++-dev protobuf-compiler-grpc
if(CVISLAM_BUILD_SERVER)
  find_package(SQLite3 REQUIRED)                      # libsqlite3-dev (the server's map store; CMake's FindSQLite3)
  # libpq-dev: the replicas' shared store and mission leases (server_cloud/cluster). libpq ships no CMake config.
  find_package(PkgConfig REQUIRED)
  pkg_check_modules(LIBPQ REQUIRED IMPORTED_TARGET libpq)
  find_package(prometheus-cpp REQUIRED CONFIG)        # prometheus-cpp-dev (the metrics endpoint: core and pull)
  # The live viewer's endpoint: websocketpp (libwebsocketpp-dev, header-only) on standalone asio (libasio-dev), TLS
  # through OpenSSL (libssl-dev). websocketpp 0.8.2 does not compile as C++20: its constructors are declared with
  # template-ids (upstream issues 991 and 1068). The build uses a copy of its headers with those names plain.
  find_package(OpenSSL REQUIRED)
  find_package(Threads REQUIRED)
  find_path(CVISLAM_WEBSOCKETPP_DIR websocketpp/server.hpp REQUIRED)
  find_path(CVISLAM_ASIO_DIR asio.hpp REQUIRED)
  set(CVISLAM_WEBSOCKETPP_COPY "${CMAKE_BINARY_DIR}/third_party/websocketpp-cxx20")
  if(NOT EXISTS "${CVISLAM_WEBSOCKETPP_COPY}/websocketpp/server.hpp")
    file(COPY "${CVISLAM_WEBSOCKETPP_DIR}/websocketpp" DESTINATION "${CVISLAM_WEBSOCKETPP_COPY}")
    foreach(_header logger/basic.hpp logger/syslog.hpp endpoint.hpp roles/server_endpoint.hpp
                    roles/client_endpoint.hpp)
      execute_process(
        COMMAND sed -E -i "s/^(\\s*)(~?)(basic|syslog|endpoint|server|client)<[a-z_, ]+>\\(/\\1\\2\\3(/"
                "${CVISLAM_WEBSOCKETPP_COPY}/websocketpp/${_header}"
        RESULT_VARIABLE _sed_result)
      if(NOT _sed_result EQUAL 0)
        message(FATAL_ERROR "could not make the C++20 copy of websocketpp/${_header}")
      endif()
    endforeach()
  endif()
  add_library(cvislam_websocketpp INTERFACE)
  target_include_directories(cvislam_websocketpp SYSTEM INTERFACE "${CVISLAM_WEBSOCKETPP_COPY}" "${CVISLAM_ASIO_DIR}")
  target_compile_definitions(cvislam_websocketpp INTERFACE ASIO_STANDALONE _WEBSOCKETPP_CPP11_STL_)
  target_link_libraries(cvislam_websocketpp INTERFACE OpenSSL::SSL OpenSSL::Crypto Threads::Threads)
endif()

# libdeflate-dev: the agent's PNG decoding (common/dataset/png_gray.cpp). Its CMake config came only in 1.15;
# find_path/find_library look inside the sysroot when cross-compiling.
find_path(LIBDEFLATE_INCLUDE_DIR libdeflate.h REQUIRED)
find_library(LIBDEFLATE_LIBRARY NAMES deflate REQUIRED)
add_library(cvislam::libdeflate UNKNOWN IMPORTED)
set_target_properties(cvislam::libdeflate PROPERTIES IMPORTED_LOCATION "${LIBDEFLATE_LIBRARY}"
  INTERFACE_INCLUDE_DIRECTORIES "${LIBDEFLATE_INCLUDE_DIR}")

# common/mcap: zstd and LZ4 (frame format) chunk compression, zlib's CRC-32. libzstd-dev, liblz4-dev, zlib1g-dev.
# Found like libdeflate (no pkg-config), so that a cross build takes them from the sysroot.
find_path(ZSTD_INCLUDE_DIR zstd.h REQUIRED)
find_library(ZSTD_LIBRARY NAMES zstd REQUIRED)
add_library(cvislam::zstd UNKNOWN IMPORTED)
set_target_properties(cvislam::zstd PROPERTIES IMPORTED_LOCATION "${ZSTD_LIBRARY}"
  INTERFACE_INCLUDE_DIRECTORIES "${ZSTD_INCLUDE_DIR}")
find_path(LZ4_INCLUDE_DIR lz4frame.h REQUIRED)
find_library(LZ4_LIBRARY NAMES lz4 REQUIRED)
add_library(cvislam::lz4 UNKNOWN IMPORTED)
set_target_properties(cvislam::lz4 PROPERTIES IMPORTED_LOCATION "${LZ4_LIBRARY}"
  INTERFACE_INCLUDE_DIRECTORIES "${LZ4_INCLUDE_DIR}")
find_package(ZLIB REQUIRED)                           # zlib1g-dev (CMake's FindZLIB: ZLIB::ZLIB)

# OpenCV: Debian ships OpenCVConfig.cmake only in the full libopencv-dev (+330 MB: VTK, dnn, contrib).
# We install the per-module -dev packages and fall back to a small find-module; see docs/development.md, "Dependencies".
find_package(OpenCV 4 QUIET CONFIG COMPONENTS core imgproc imgcodecs features2d calib3d)
if(NOT OpenCV_FOUND)
  # features2d and calib3d: ORB and an independent camera projection in the simulator's tests
  set(OpenCV_MIN_MODULES core imgproc imgcodecs features2d calib3d)
  include(OpenCVMinimal)
endif()

if(CVISLAM_BUILD_TESTS)
  find_package(GTest REQUIRED CONFIG)                 # libgtest-dev libgmock-dev
  include(GoogleTest)
endif()
if(CVISLAM_BUILD_BENCHMARKS)
  find_package(benchmark REQUIRED CONFIG)             # libbenchmark-dev
endif()

# Cross-compiling against a sysroot (toolchains/aarch64-linux-gnu.cmake): package configs written for the
# board's own /usr must be pointed into the sysroot. (gRPC's code generators: see toolchains/make_sysroot.sh.)
if(CMAKE_CROSSCOMPILING AND CMAKE_SYSROOT)
  # Ceres' exported targets name /usr/lib/<triple>/liblapack.so and friends by absolute path.
  get_target_property(_ceres_libs Ceres::ceres INTERFACE_LINK_LIBRARIES)
  if(_ceres_libs)
    list(TRANSFORM _ceres_libs REPLACE "^/usr/" "${CMAKE_SYSROOT}/usr/")
    set_target_properties(Ceres::ceres PROPERTIES INTERFACE_LINK_LIBRARIES "${_ceres_libs}")
  endif()
endif()
