/* Lifecycle client on the eProsima Micro XRCE-DDS Client v2.4.3 library (built from source
 * outside the repository; compile: gcc -O2 -o lifecycle_client lifecycle_client.c
 * -I$PREFIX/include -L$PREFIX/lib -lmicroxrcedds_client -lmicrocdr).
 * pattern "uros": rmw_microxrcedds's creation (binary, REPLACE|REUSE, one request per round
 *   trip, talker on rt/chatter + /add_two_ints replier + READ_DATA), reliable strings.
 * pattern "px4": uxrce_dds_client's (session-less ping, participant by XML with REPLACE,
 *   topic/publisher/writer binary with REPLACE, best-effort strings at 50 Hz).
 * Prints "ROUND r <monotonic s>" when round r starts (its reset), writes "Hello World: N". */
#include <uxr/client/client.h>
#include <ucdr/microcdr.h>
#include <uxr/client/util/ping.h>
#include <stdio.h>
#include <string.h>
#include <stdlib.h>
#include <time.h>
#include <unistd.h>
#define HIST 4
#define BUF (UXR_CONFIG_UDP_TRANSPORT_MTU * HIST)
static double mono(void){struct timespec t;clock_gettime(CLOCK_MONOTONIC,&t);return t.tv_sec+t.tv_nsec/1e9;}
static int one(uxrSession* s, uint16_t req){uint8_t st=0xff; uint16_t r=req; uxr_run_session_until_all_status(s,1000,&r,&st,1); return st;}
int main(int argc, char** argv){
    if (argc < 6) { printf("usage: ip port uros|px4 n rounds [domain]\n"); return 2; }
    int px4 = !strcmp(argv[3], "px4"); int n = atoi(argv[4]), rounds = atoi(argv[5]);
    int domain = argc > 6 ? atoi(argv[6]) : 0; int counter = 0;
    for (int r = 0; r < rounds; r++) {
        printf("ROUND %d %.6f\n", r, mono()); fflush(stdout);
        uxrUDPTransport tr;
        if (!uxr_init_udp_transport(&tr, UXR_IPv4, argv[1], argv[2])) { printf("transport\n"); return 1; }
        if (px4) while (!uxr_ping_agent_attempts(&tr.comm, 1000, 1)) {}
        uxrSession s; uxr_init_session(&s, &tr.comm, px4 ? 0x00000001 : 0x00AB0001);
        if (!uxr_create_session(&s)) { printf("session FAILED\n"); return 1; }
        printf("SESSION %d %.6f\n", r, mono()); fflush(stdout);
        uint8_t ob[BUF], ib[BUF], beo[UXR_CONFIG_UDP_TRANSPORT_MTU];
        uxrStreamId rel = uxr_create_output_reliable_stream(&s, ob, BUF, HIST);
        uxrStreamId be = uxr_create_output_best_effort_stream(&s, beo, sizeof beo);
        uxr_create_input_reliable_stream(&s, ib, BUF, HIST);
        uxr_create_input_best_effort_stream(&s);
        uint8_t mode = px4 ? UXR_REPLACE : (UXR_REPLACE | UXR_REUSE);
        uxrObjectId part = uxr_object_id(px4 ? 1 : 0, UXR_PARTICIPANT_ID), topic = uxr_object_id(0, UXR_TOPIC_ID);
        uxrObjectId pub = uxr_object_id(0, UXR_PUBLISHER_ID), dw = uxr_object_id(0, UXR_DATAWRITER_ID);
        int st[6] = {0}; int k = 0;
        if (px4) {
            st[k++] = one(&s, uxr_buffer_create_participant_xml(&s, rel, part, domain,
                "<dds><participant><rtps><name>/px4_micro_xrce_dds</name></rtps></participant></dds>", mode));
        } else {
            st[k++] = one(&s, uxr_buffer_create_participant_bin(&s, rel, part, domain, "talker", mode));
        }
        st[k++] = one(&s, uxr_buffer_create_topic_bin(&s, rel, topic, part, "rt/chatter", "std_msgs::msg::dds_::String_", mode));
        st[k++] = one(&s, uxr_buffer_create_publisher_bin(&s, rel, pub, part, mode));
        uxrQoS_t q = px4
            ? (uxrQoS_t){.durability = UXR_DURABILITY_TRANSIENT_LOCAL, .reliability = UXR_RELIABILITY_BEST_EFFORT, .history = UXR_HISTORY_KEEP_LAST, .depth = 0}
            : (uxrQoS_t){.durability = UXR_DURABILITY_VOLATILE, .reliability = UXR_RELIABILITY_RELIABLE, .history = UXR_HISTORY_KEEP_LAST, .depth = 10};
        st[k++] = one(&s, uxr_buffer_create_datawriter_bin(&s, rel, dw, pub, topic, q, mode));
        if (!px4) {
            uxrObjectId rep = uxr_object_id(0, UXR_REPLIER_ID);
            uxrQoS_t sq = {.durability = UXR_DURABILITY_VOLATILE, .reliability = UXR_RELIABILITY_RELIABLE, .history = UXR_HISTORY_KEEP_LAST, .depth = 5};
            st[k++] = one(&s, uxr_buffer_create_replier_bin(&s, rel, rep, part, "/add_two_ints",
                "example_interfaces::srv::dds_::AddTwoInts_Request_", "example_interfaces::srv::dds_::AddTwoInts_Response_",
                "rq/add_two_intsRequest", "rr/add_two_intsReply", sq, mode));
            uxrDeliveryControl dc = {0}; dc.max_samples = UXR_MAX_SAMPLES_UNLIMITED;
            uxr_buffer_request_data(&s, rel, rep, (uxrStreamId){0, UXR_RELIABLE_STREAM, UXR_INPUT_STREAM}, &dc);
        }
        printf("CREATED %d %.6f statuses", r, mono()); for (int i = 0; i < k; i++) printf(" %d", st[i]); printf("\n"); fflush(stdout);
        for (int i = 0; i < n; i++) {
            char txt[64]; snprintf(txt, sizeof txt, "Hello World: %d", counter++);
            uint32_t len = strlen(txt) + 1; ucdrBuffer ub;
            uxr_prepare_output_stream(&s, px4 ? be : rel, dw, &ub, 4 + len);
            ucdr_serialize_string(&ub, txt);
            if (px4) { uxr_flash_output_streams(&s); uxr_run_session_time(&s, 20); }
            else { uxr_run_session_until_confirm_delivery(&s, 1000); uxr_run_session_time(&s, 50); }
        }
        printf("WROTE %d %.6f\n", r, mono()); fflush(stdout);
        uxr_close_udp_transport(&tr);   /* reset: no DELETE */
        usleep(300000);
    }
    return 0;
}
