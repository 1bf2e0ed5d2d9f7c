// A client built against the reference OpenIGTLink library as Debian ships it (libopenigtlink-dev
// 1.11), for tests/integration/test_igtl_reference.py (issue #23).
//
//   igtl_ref_client HOST PORT N_V1 N_V2
//
// Phase 1 (never writes): reads header-version-1 TRANSFORMs the way the library's ReceiveClient
// example does (igtl::MessageHeader::Unpack, igtl::TransformMessage::Unpack(1) with its CRC check)
// until N_V1 of them were RobotToImage (ToolToImage comes at the robot link rate, RobotToImage
// at the re-send period), printing one line each:
//     V1 <device> crc=<ok|bad> <m00 m01 m02 m03 m10 ... m23>      (the upper 3x4, row-major, mm)
// Any other header version in phase 1 prints "UNEXPECTED <version> <type> <device>" and exits 3;
// other version-1 messages (the PhantomSpheres POINT) are read past: "SKIP 1 <type> <device>".
//
// Phase 2: sends a header-version-2 STATUS (OK, no metadata), as SlicerOpenIGTLink does at connect
// (PR #65), prints "SENT_V2_STATUS", then reads until N_V2 version-2 RobotToImage messages came.  The 1.11 library
// unpacks only version-1 headers, so this phase decodes the 58-byte header with the library's C
// layer (igtl_header + igtl_header_convert_byte_order), checks the body CRC with its crc64(), and
// splits the extended header and metadata with a few lines here (v3_proposal.md):
//     V<version> <type> <device> crc=<ok|bad> body=<n> [meta <key>=<value>;...]
// Exit status: 0 done, 2 connection / read failure, 3 protocol surprise.
//
//   igtl_ref_client HOST PORT query [DEVICE]
//
// Query mode (issue #31): sends, as version 1 with the library's own classes, GET_TRANS for
// DEVICE (default ToolToImage; igtl::GetTransformMessage), GET_STATUS (device "RefClient"), GET_CAPABIL and
// GET_POINT for PhantomSpheres, then reads until it has seen a TRANSFORM (or a STATUS) for DEVICE, a STATUS
// RefClient, a CAPABILITY and a POINT, each unpacked by the library with its CRC check:
//     TRANSFORM <device> crc=<ok|bad>
//     STATUS <device> crc=<ok|bad> code=<C> name=<error name> text=<status string>
//     CAPABILITY <device> crc=<ok|bad> types=<T1,T2,...>
//     POINT <device> crc=<ok|bad> n=<N>, then per point: PT <name>|<x> <y> <z>|<diameter>

#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <vector>

#include "igtlCapabilityMessage.h"
#include "igtlClientSocket.h"
#include "igtlMessageHeader.h"
#include "igtlPointMessage.h"
#include "igtlStatusMessage.h"
#include "igtlTransformMessage.h"
#include "igtl_header.h"
#include "igtl_util.h"

static unsigned be16(const unsigned char* p) { return (unsigned(p[0]) << 8) | p[1]; }
static unsigned long be32(const unsigned char* p) {
  return (static_cast<unsigned long>(be16(p)) << 16) | be16(p + 2);
}

static int phase1(igtl::ClientSocket::Pointer& socket, int n) {
  igtl::MessageHeader::Pointer header = igtl::MessageHeader::New();
  int got = 0;
  while (got < n) {
    header->InitPack();
    if (socket->Receive(header->GetPackPointer(), header->GetPackSize()) != header->GetPackSize()) {
      std::printf("READ_FAILED header\n");
      return 2;
    }
    const unsigned char* raw = static_cast<const unsigned char*>(header->GetPackPointer());
    if (be16(raw) != 1) {
      char type[13] = {0}, dev[21] = {0};
      std::memcpy(type, raw + 2, 12);
      std::memcpy(dev, raw + 14, 20);
      std::printf("UNEXPECTED %u %s %s\n", be16(raw), type, dev);
      return 3;
    }
    header->Unpack();
    if (std::strcmp(header->GetDeviceType(), "TRANSFORM") != 0) {  // POINT, STATUS: read past
      std::vector<unsigned char> skip(header->GetBodySizeToRead());
      if (!skip.empty() && socket->Receive(skip.data(), static_cast<int>(skip.size())) != static_cast<int>(skip.size())) {
        std::printf("READ_FAILED body\n");
        return 2;
      }
      std::printf("SKIP 1 %s %s\n", header->GetDeviceType(), header->GetDeviceName());
      continue;
    }
    igtl::TransformMessage::Pointer msg = igtl::TransformMessage::New();
    msg->SetMessageHeader(header);
    msg->AllocatePack();
    if (socket->Receive(msg->GetPackBodyPointer(), msg->GetPackBodySize()) != msg->GetPackBodySize()) {
      std::printf("READ_FAILED body\n");
      return 2;
    }
    int c = msg->Unpack(1);  // 1: check the CRC64
    igtl::Matrix4x4 m;
    msg->GetMatrix(m);
    std::printf("V1 %s crc=%s", msg->GetDeviceName(), (c & igtl::MessageHeader::UNPACK_BODY) ? "ok" : "bad");
    for (int r = 0; r < 3; ++r)
      for (int k = 0; k < 4; ++k) std::printf(" %.9g", static_cast<double>(m[r][k]));
    std::printf("\n");
    if (std::strcmp(msg->GetDeviceName(), "RobotToImage") == 0) ++got;
  }
  return 0;
}

static int send_v2_status(igtl::ClientSocket::Pointer& socket) {
  igtl::StatusMessage::Pointer status = igtl::StatusMessage::New();
  status->SetDeviceName("RefClient");
  status->SetCode(igtl::StatusMessage::STATUS_OK);
  status->SetStatusString("reads header version 2");
  status->Pack();  // the library packs version 1: re-frame its content as a version-2 body
  const unsigned char* content = static_cast<const unsigned char*>(status->GetPackBodyPointer());
  const int content_size = status->GetPackBodySize();
  std::vector<unsigned char> body;
  const unsigned char ext[12] = {0, 12, 0, 2, 0, 0, 0, 0, 0, 0, 0, 1};  // 12, mhead 2, meta 0, MSG_ID 1
  body.insert(body.end(), ext, ext + 12);
  body.insert(body.end(), content, content + content_size);
  body.push_back(0);  // metadata header: INDEX_COUNT = 0
  body.push_back(0);
  igtl_header h;
  std::memcpy(&h, status->GetPackPointer(), IGTL_HEADER_SIZE);
  igtl_header_convert_byte_order(&h);  // network → host
  h.version = 2;
  h.body_size = body.size();
  h.crc = crc64(body.data(), body.size(), 0ULL);
  igtl_header_convert_byte_order(&h);  // host → network
  if (socket->Send(&h, IGTL_HEADER_SIZE) == 0 || socket->Send(body.data(), static_cast<int>(body.size())) == 0) {
    std::printf("SEND_FAILED\n");
    return 2;
  }
  std::printf("SENT_V2_STATUS\n");
  return 0;
}

static int phase2(igtl::ClientSocket::Pointer& socket, int n) {
  int got = 0;
  while (got < n) {
    igtl_header h;
    if (socket->Receive(&h, IGTL_HEADER_SIZE) != IGTL_HEADER_SIZE) {
      std::printf("READ_FAILED header\n");
      return 2;
    }
    igtl_header_convert_byte_order(&h);
    std::vector<unsigned char> body(h.body_size);
    if (h.body_size > 0 && socket->Receive(body.data(), static_cast<int>(h.body_size)) != static_cast<int>(h.body_size)) {
      std::printf("READ_FAILED body\n");
      return 2;
    }
    char type[13] = {0}, dev[21] = {0};
    std::memcpy(type, h.name, 12);
    std::memcpy(dev, h.device_name, 20);
    const bool crc_ok = crc64(body.data(), h.body_size, 0ULL) == h.crc;
    std::printf("V%u %s %s crc=%s body=%llu", h.version, type, dev, crc_ok ? "ok" : "bad",
                static_cast<unsigned long long>(h.body_size));
    if (h.version == 2) {
      if (body.size() < 12) { std::printf(" SHORT\n"); return 3; }
      const unsigned ext_size = be16(&body[0]);
      const unsigned mhead_size = be16(&body[2]);
      const unsigned long meta_size = be32(&body[4]);
      if (ext_size + mhead_size + meta_size > body.size() || mhead_size < 2) { std::printf(" BAD_EXT\n"); return 3; }
      const unsigned char* mh = &body[body.size() - meta_size - mhead_size];
      const unsigned char* md = mh + mhead_size;
      const unsigned count = be16(mh);
      std::printf(" meta");
      unsigned long pos = 0;
      for (unsigned i = 0; i < count; ++i) {
        const unsigned char* item = mh + 2 + 8 * i;
        const unsigned ks = be16(item);
        const unsigned long vs = be32(item + 4);
        if (pos + ks + vs > meta_size) { std::printf(" BAD_META\n"); return 3; }
        std::string key(reinterpret_cast<const char*>(md + pos), ks);
        std::string value(reinterpret_cast<const char*>(md + pos + ks), vs);
        pos += ks + vs;
        std::printf(" %s=%s;", key.c_str(), value.c_str());
      }
      if (std::strcmp(dev, "RobotToImage") == 0) ++got;
    }
    std::printf("\n");
  }
  return 0;
}

static bool send_packed(igtl::ClientSocket::Pointer& socket, igtl::MessageBase* msg) {
  msg->Pack();
  return socket->Send(msg->GetPackPointer(), msg->GetPackSize()) != 0;
}

template <class M>
static int receive_into(igtl::ClientSocket::Pointer& socket, igtl::MessageHeader::Pointer& header,
                        typename M::Pointer& msg) {
  msg->SetMessageHeader(header);
  msg->AllocatePack();
  if (socket->Receive(msg->GetPackBodyPointer(), msg->GetPackBodySize()) != msg->GetPackBodySize()) return -1;
  return (msg->Unpack(1) & igtl::MessageHeader::UNPACK_BODY) ? 1 : 0;  // 1: CRC ok
}

static int query(igtl::ClientSocket::Pointer& socket, const std::string& trans_device) {
  igtl::GetTransformMessage::Pointer get_trans = igtl::GetTransformMessage::New();
  get_trans->SetDeviceName(trans_device.c_str());
  igtl::GetStatusMessage::Pointer get_status = igtl::GetStatusMessage::New();
  get_status->SetDeviceName("RefClient");
  igtl::GetCapabilityMessage::Pointer get_capabil = igtl::GetCapabilityMessage::New();
  get_capabil->SetDeviceName("RefClient");
  igtl::GetPointMessage::Pointer get_point = igtl::GetPointMessage::New();
  get_point->SetDeviceName("PhantomSpheres");
  if (!send_packed(socket, get_trans) || !send_packed(socket, get_status) || !send_packed(socket, get_capabil) ||
      !send_packed(socket, get_point)) {
    std::printf("SEND_FAILED\n");
    return 2;
  }
  bool got_transform = false, got_status = false, got_capability = false, got_point = false;
  igtl::MessageHeader::Pointer header = igtl::MessageHeader::New();
  for (int i = 0; i < 500 && !(got_transform && got_status && got_capability && got_point); ++i) {
    header->InitPack();
    if (socket->Receive(header->GetPackPointer(), header->GetPackSize()) != header->GetPackSize()) {
      std::printf("READ_FAILED header\n");
      return 2;
    }
    header->Unpack();
    const std::string type = header->GetDeviceType();
    const std::string dev = header->GetDeviceName();
    int c = 0;
    if (type == "TRANSFORM") {
      igtl::TransformMessage::Pointer m = igtl::TransformMessage::New();
      c = receive_into<igtl::TransformMessage>(socket, header, m);
      std::printf("TRANSFORM %s crc=%s\n", dev.c_str(), c == 1 ? "ok" : "bad");
      got_transform = got_transform || dev == trans_device;
    } else if (type == "STATUS") {
      igtl::StatusMessage::Pointer m = igtl::StatusMessage::New();
      c = receive_into<igtl::StatusMessage>(socket, header, m);
      std::printf("STATUS %s crc=%s code=%d name=%s text=%s\n", dev.c_str(), c == 1 ? "ok" : "bad",
                  m->GetCode(), m->GetErrorName(), m->GetStatusString());
      got_status = got_status || dev == "RefClient";
      got_transform = got_transform || dev == trans_device;  // an invalid device is answered by STATUS
      got_point = got_point || dev == "PhantomSpheres";    // so is a POINT list with no registration
    } else if (type == "CAPABILITY") {
      igtl::CapabilityMessage::Pointer m = igtl::CapabilityMessage::New();
      c = receive_into<igtl::CapabilityMessage>(socket, header, m);
      std::printf("CAPABILITY %s crc=%s types=", dev.c_str(), c == 1 ? "ok" : "bad");
      std::vector<std::string> types = m->GetTypes();
      for (size_t k = 0; k < types.size(); ++k) std::printf("%s%s", k ? "," : "", types[k].c_str());
      std::printf("\n");
      got_capability = true;
    } else if (type == "POINT") {
      igtl::PointMessage::Pointer m = igtl::PointMessage::New();
      c = receive_into<igtl::PointMessage>(socket, header, m);
      std::printf("POINT %s crc=%s n=%d\n", dev.c_str(), c == 1 ? "ok" : "bad", m->GetNumberOfPointElement());
      for (int k = 0; k < m->GetNumberOfPointElement(); ++k) {
        igtl::PointElement::Pointer e;
        m->GetPointElement(k, e);
        igtlFloat32 x, y, z;
        e->GetPosition(x, y, z);
        std::printf("PT %s|%.9g %.9g %.9g|%.9g\n", e->GetName(), x, y, z, e->GetRadius());
      }
      got_point = true;
    } else {
      std::printf("UNEXPECTED 1 %s %s\n", type.c_str(), dev.c_str());
      return 3;
    }
    if (c < 0) {
      std::printf("READ_FAILED body\n");
      return 2;
    }
  }
  return (got_transform && got_status && got_capability && got_point) ? 0 : 3;
}

int main(int argc, char* argv[]) {
  if ((argc == 4 || argc == 5) && std::strcmp(argv[3], "query") == 0) {
    igtl::ClientSocket::Pointer socket = igtl::ClientSocket::New();
    if (socket->ConnectToServer(argv[1], std::atoi(argv[2])) != 0) {
      std::printf("CONNECT_FAILED\n");
      return 2;
    }
    socket->SetReceiveTimeout(10000);
    int rc = query(socket, argc == 5 ? argv[4] : "ToolToImage");
    std::fflush(stdout);
    socket->CloseSocket();
    return rc;
  }
  if (argc != 5) {
    std::fprintf(stderr, "usage: %s HOST PORT N_V1 N_V2 | %s HOST PORT query [DEVICE]\n", argv[0], argv[0]);
    return 2;
  }
  igtl::ClientSocket::Pointer socket = igtl::ClientSocket::New();
  if (socket->ConnectToServer(argv[1], std::atoi(argv[2])) != 0) {
    std::printf("CONNECT_FAILED\n");
    return 2;
  }
  socket->SetReceiveTimeout(10000);  // ms: a silent server ends the client instead of hanging it
  int rc = phase1(socket, std::atoi(argv[3]));
  if (rc == 0) rc = send_v2_status(socket);
  if (rc == 0) rc = phase2(socket, std::atoi(argv[4]));
  std::fflush(stdout);
  socket->CloseSocket();
  return rc;
}
